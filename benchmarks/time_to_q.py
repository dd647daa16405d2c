"""Time to discharge: fieldtool vs pyorc (pyopenrivercam), end to end from the video to Q, on the same clips.

    .venv/bin/python benchmarks/time_to_q.py                       # 720p 8 s + 1080p 30 s (+ fast_1080p), 3 runs
    .venv/bin/python benchmarks/time_to_q.py --clips 720p --repeats 5
    .venv/bin/python benchmarks/time_to_q.py --engines             # engine table: fieldtool, OpenPIV, ffpiv, RIVeR
    .venv/bin/python benchmarks/time_to_q.py --profile             # cProfile top entries, 720p, before/after
    .venv/bin/python benchmarks/time_to_q.py --clips 720p_8s --sweep --sweep-peers river --river   # RIVeR too
    .venv/bin/python benchmarks/time_to_q.py --cores 1 --clips 720p_8s,fast_1080p   # every contestant on 1 core

Clips (rendered once into --root by the generator, exact truth from ``River.truth()``): the ``oblique`` scene
at 1280x720 for 8 s, the same at 1920x1080 for 30 s, and helper robust's ``fast_1080p`` hard preset when
``fieldtool.synthetic.presets`` has it. Every project runs with default settings and no ROI (``roi.rect_px``
cleared), as the issue measured.

Contestants, each a separate process started from here (interpreter start and imports included, as a user
waits for them), in turn within every repeat (alternating runs), medians over the repeats:
* ``fieldtool``: ``python -m fieldtool.cli.main run project.toml --out NEW`` with the defaults
  (``[piv] region = "section"``, pairs added until the discharge converged); all outputs (plots) written.
* ``pyorc``: ``benchmarks/peers/pyorc_run.py`` in its own virtual environment ``benchmarks/.peers-venv``
  (created here with the pinned versions in PEERS; never the project's venv), pyorc's API recipe with the same
  GCPs, level, velocity index and cross-section, a bounding box of +-3 m around the section (as the ROI of the
  generated project), at its most accurate setting of the last ``--sweep`` (``peer_settings.json``: resolution
  0.01-0.08 m x window 10-64 px; without a sweep 0.03 m / 32 px, the issue's).
* ``thesis (OpenPIV rust)``: ``benchmarks/peers/openpiv_thesis.py``, the thesis' method (single pass, nearest
  vector) on OpenPIV with its Rust backend, at its most accurate window and s2n threshold of the sweep.
* ``decode only (PyAV)``: ``benchmarks/peers/decode_floor.py``, every frame decoded with all threads: the floor.
* once per clip, not alternated (it is the slow reference): fieldtool full frame, every pair
  (``region = "full"``, ``all_pairs = true``): "today's full-frame all-pairs result" of the issue
  (``--no-reference`` leaves it out).

Printed per clip: median wall time and every run's, the ratio pyorc / fieldtool (ratio of medians and median of
the per-run ratios), each discharge and its error against the truth, the difference in percentage points
between fieldtool's default and its full-frame all-pairs error, pairs used, fieldtool's frames decoded against the
frames in its range (result.json ``piv_sampling``; "no Q" where a contestant gave none), the peak resident memory
of each process (``wait4``'s ru_maxrss) and the load average before and after. Not part of the test run.

``--cores N``: this process, and so every contestant it starts, runs on N of the cores it may use (its CPU
affinity, as ``taskset``): how each contestant's time scales with the cores (2 and 1 here; the header line says
how many each set had).

``--engines``: pairs/s on the same 1920x1080 pairs (window 32, overlap 16): fieldtool's engine, OpenPIV 0.26 (its
SciPy and Rust backends), ffpiv, and RIVeR's engine (``peers/river_rate.py`` in ``benchmarks/.river-venv``, pinned
``river-cli``: RIVeR 3.x's Python port of PIVlab's ``piv_FFTmulti``, one pair a run).

``--river``: RIVeR end to end as a contestant too (``peers/river_run.py`` in ``benchmarks/.river-venv``: its own
workflow, every frame written as a JPEG file, its PIV on every consecutive pair of the project's ROI, its section
and discharge; at the most accurate interrogation area of ``--sweep --sweep-peers river``). Slow: left out by
default.
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PEERS_VENV = HERE / ".peers-venv"
# pinned (pip index versions, Dec 2026): pyorc and its engine, OpenPIV with its Rust backend, PyAV for the floor
PEERS = ["pyopenrivercam==0.9.10", "ffpiv==0.2.1", "openpiv==0.26.1", "openpiv-rust==0.26.1", "av==18.1.0"]
# pyorc's main settings as a competent user sweeps them (resolution m, window px): the most accurate on the sweep
# clip is used on every clip (``--sweep`` measures it and writes SETTINGS; without it the last sweep's is used)
# (stop 34: the grid reaches past 0.05 m / 32 px, the most accurate of the smaller grid, which sat on its corner)
PYORC_SWEEP = [(r, w) for r in (0.01, 0.02, 0.03, 0.05, 0.08) for w in (10, 16, 24, 32, 48, 64)]
# the thesis' method on OpenPIV's Rust backend: window px (overlap half of it) and peak-to-peak s2n threshold
THESIS_SWEEP = [(w, s) for w in (16, 24, 32, 48, 64) for s in (0.0, 1.05, 1.2, 1.4)]
SETTINGS = HERE / "peer_settings.json"
# RIVeR's Python engine (river-cli, a port of PIVlab's piv_FFTmulti) in a venv of its own: it pins its own
# OpenCV, SciPy < 1.14, numba and pyFFTW
RIVER_VENV = HERE / ".river-venv"
RIVER = ["river-cli==3.7.0"]
# RIVeR's main setting, its interrogation area (px; its second pass takes half of it): RIVeR's default is 128
RIVER_SWEEP = [32, 64, 96, 128, 192]


def cores() -> int:
    """The cores this process may run on (its affinity: ``--cores``, ``taskset``), which its children inherit."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def limit_cores(n: int) -> None:
    """Run this process and every contestant it starts on the first ``n`` cores it may use (``--cores``)."""
    allowed = sorted(os.sched_getaffinity(0))
    if not 1 <= n <= len(allowed):
        raise ValueError(f"--cores {n}: this machine lets the benchmark use 1 to {len(allowed)} cores")
    os.sched_setaffinity(0, allowed[:n])


def byte_compile(tree: Path = REPO) -> None:
    """``tree``'s fieldtool modules byte-compiled before its runs are timed, as pip does for an installed package
    (pyorc's are): an editable install where PYTHONDONTWRITEBYTECODE is set would otherwise compile about 50
    modules on every run (0.1 s)."""
    compileall.compile_dir(str(tree / "fieldtool"), quiet=1)


# --------------------------------------------------------------------------------------------- clips


def clips(root: Path, names: list[str]) -> list[dict]:
    """Render the clips once; return [{name, dir, project (no ROI), truth, spec}]."""
    from fieldtool.synthetic import presets, render_scene

    plan = {"720p_8s": lambda: presets.get("oblique", duration_s=8.0),
            "1080p_30s": lambda: presets.get("oblique", duration_s=30.0, camera__width_px=1920, camera__height_px=1080),
            "4k_drone": lambda: presets.get("drone_4k") if "drone_4k" in getattr(presets, "HARD_NAMES", ())
            else presets.get("nadir", duration_s=8.0, camera__width_px=3840, camera__height_px=2160)}
    if "fast_1080p" in getattr(presets, "NAMES", ()) + tuple(getattr(presets, "HARD_NAMES", ())):
        plan["fast_1080p"] = lambda: presets.get("fast_1080p")
    out = []
    for name in names:
        if name not in plan:
            print(f"clip {name}: not available here (fieldtool.synthetic.presets has no such preset); skipped")
            continue
        d = root / name
        spec = plan[name]()
        if not (d / "truth.json").is_file():
            t0 = time.perf_counter()
            render_scene(spec, d)
            print(f"rendered {name} in {time.perf_counter() - t0:.0f} s")
        import tomlkit

        doc = tomlkit.parse((d / "project.toml").read_text())
        doc["roi"]["rect_px"] = []
        (d / "noroi.toml").write_text(tomlkit.dumps(doc))
        doc["piv"]["region"] = "full"
        doc["piv"]["all_pairs"] = True
        (d / "full_all.toml").write_text(tomlkit.dumps(doc))
        out.append({"name": name, "dir": d, "truth": json.loads((d / "truth.json").read_text()), "spec": spec})
    return out


def pyorc_job(c: dict, setting: tuple[float, int]) -> Path:
    """The job file of pyorc_run.py: what a pyorc user enters for this clip (see the module docstring), at
    ``setting`` = (resolution m, window px)."""
    import tomllib

    d, spec, tr = c["dir"], c["spec"], c["truth"]
    r = spec.river
    proj = tomllib.loads((d / "noroi.toml").read_text())
    cs = np.loadtxt(d / "cross_section.csv", delimiter=",", skiprows=1)
    xs, half = r.x_section_m, spec.roi_half_length_m
    y_hi, y_lo = r.y_left_edge + 0.5, r.y_right_edge - 0.5
    job = {"video": str(d / spec.video_name), "width": spec.camera.width_px, "height": spec.camera.height_px,
           "n_frames": int(tr["n_frames"]), "gcp_px": proj["ortho"]["gcp_px"],
           "gcp_xy_m": [g[:2] for g in tr["gcp_world_m"]], "level_m": float(tr["water_level_m"]),
           "window_size": int(setting[1]), "resolution_m": float(setting[0]),
           # pyorc spans its grid from the first edge of the box towards the third corner: start on the left bank
           "bbox_xy_m": [[xs - half, y_hi], [xs + half, y_hi], [xs + half, y_lo], [xs - half, y_lo]],
           "transect_xyz_m": [[float(xs), float(r.y_of_station(s)), float(z)] for s, z in cs],
           "alpha": float(proj["section"].get("alpha") or 0.85), "s_max": 3.0 * float(r.u_max_ms)}
    path = d / f"pyorc_job_{setting[0]:g}_{setting[1]}.json"
    path.write_text(json.dumps(job))
    return path


def thesis_job(c: dict, setting: tuple[int, float]) -> Path:
    """The job file of openpiv_thesis.py at ``setting`` = (window px, s2n threshold): the clip, the generated
    project's ROI (the box the thesis' user draws), and the geometry the thesis' steps compute before the
    discharge (homography of the GCPs, the section's subsection centres, their areas, the section's normal)."""
    from fieldtool.processing import discharge as dq
    from fieldtool.project.model import load_project
    from fieldtool.run import geometry
    from fieldtool.run.inputs import load_inputs

    d, spec, tr = c["dir"], c["spec"], c["truth"]
    proj = load_project(d / "project.toml")
    inputs = load_inputs(proj)
    level, mapping = geometry.level_and_mapping(proj, inputs)
    geom = geometry.build_section(proj, inputs, level.level_m, mapping)
    area, _ = dq.subsection_areas(geom, inputs.cross_section, level.level_m)
    alpha = dq.resolve_alpha(proj.section.alpha, inputs.cross_section, level.level_m)
    w, s2n = setting
    job = {"video": str(d / spec.video_name), "n_frames": int(tr["n_frames"]), "fps": float(tr["fps"]),
           "roi_px": [int(v) for v in proj.roi.rect_px], "window_px": int(w), "overlap_px": int(w) // 2,
           "search_px": int(w), "s2n_min": float(s2n), "backend": "rust", "H": np.asarray(mapping.H).tolist(),
           "centres_px": geom.sample_img.mean(axis=1).tolist(), "areas_m2": np.asarray(area).tolist(),
           "normal": np.asarray(geom.normal).tolist(), "alpha": float(alpha)}
    path = d / f"thesis_job_{w}_{s2n:g}.json"
    path.write_text(json.dumps(job))
    return path


def river_job(c: dict, ia: int) -> Path:
    """The job file of peers/river_run.py at interrogation area ``ia`` px: what a RIVeR user enters for this clip
    (the 4 GCPs on the water plane, the generated project's ROI as its bbox, the section's two water edges and
    its bathymetry, the level, alpha)."""
    import tomllib

    d, spec, tr = c["dir"], c["spec"], c["truth"]
    r = spec.river
    proj = tomllib.loads((d / "project.toml").read_text())
    x0, y0, x1, y1 = (int(v) for v in proj["roi"]["rect_px"])
    cs = np.loadtxt(d / "cross_section.csv", delimiter=",", skiprows=1)
    xs = float(r.x_section_m)
    job = {"video": str(d / spec.video_name), "n_frames": int(tr["n_frames"]), "fps": float(tr["fps"]),
           "gcp_px": proj["ortho"]["gcp_px"], "gcp_xy_m": [g[:2] for g in tr["gcp_world_m"]],
           "bbox_px": [x0, y0, x1 - x0, y1 - y0], "bathymetry": [[float(s), float(z)] for s, z in cs],
           "edges_en_m": [[xs, float(r.y_left_edge)], [xs, float(r.y_right_edge)]],
           "level_m": float(tr["water_level_m"]), "alpha": float(proj["section"].get("alpha") or 0.85),
           "interrogation_area_px": int(ia)}
    path = d / f"river_job_{ia}.json"
    path.write_text(json.dumps(job))
    return path


def best_settings() -> dict:
    """The peers' most accurate settings from the last ``--sweep`` (else pyorc's 0.03 m / 32 px, the issue's
    sweep, and the thesis' window 32 with no s2n threshold)."""
    if SETTINGS.is_file():
        s = json.loads(SETTINGS.read_text())
        return {"pyorc": tuple(s["pyorc"]), "thesis": tuple(s["thesis"]), "river": int(s.get("river", 128))}
    return {"pyorc": (0.03, 32), "thesis": (32, 0.0), "river": 128}


# --------------------------------------------------------------------------------------------- processes


def peers_python(venv: Path = PEERS_VENV, pins: list[str] = PEERS) -> Path:
    """A peers' venv interpreter (the peers' or RIVeR's); created with its pinned packages on first use."""
    py = venv / "bin" / "python"
    if not py.is_file():
        print(f"creating {venv} with {' '.join(pins)} (once)")
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", *pins], check=True)
    return py


def timed(cmd: list[str], env: dict | None = None, cwd: Path = REPO) -> tuple[float, int, str, float]:
    """Run ``cmd`` in ``cwd`` (a ``-c`` launcher imports fieldtool from there first); (wall s, peak resident
    memory MiB of that process, stdout, CPU s of that process and its threads: user + system, which a shared
    machine's load inflates far less than the wall time)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        p = subprocess.Popen(cmd, stdout=out, stderr=err, env=env, cwd=cwd)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text, etext = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    if p.returncode not in (0,):
        raise RuntimeError(f"{cmd[:4]} exited {p.returncode}: {etext[-800:]}")
    return wall, int(ru.ru_maxrss / 1024), text, ru.ru_utime + ru.ru_stime


def run_fieldtool(
    toml: Path, scratch: Path, launcher: tuple[str, ...] = ("-m", "fieldtool.cli.main"), tree: Path = REPO
) -> dict:
    """One ``fieldtool run`` with the defaults; ``launcher``: the interpreter's arguments before the CLI's
    (cpu_budget.py's wrapper reports the run's CPU apart from its children's on stdout, returned as "stdout");
    ``tree``: the source tree run (this repository's by default; cpu_budget.py --trees)."""
    out = Path(tempfile.mkdtemp(dir=scratch))
    env = dict(os.environ, PYTHONPATH=str(tree))
    wall, mem, text, cpu = timed([sys.executable, *launcher, "run", str(toml), "--out", str(out)], env, tree)
    res = json.loads((out / "result.json").read_text())
    shutil.rmtree(out, ignore_errors=True)
    return {"s": wall, "cpu": cpu, "mib": mem, "q": res["discharge_m3s"], "pairs": res.get("pairs_used"),
            "converged": res.get("converged"), "piv_s": res["timings_s"].get("frames_and_piv"), "stdout": text,
            "frames": tuple(res.get("piv_sampling", {}).get(k) for k in ("frames_decoded", "frames_in_range"))}


def run_peer(script: str, job: Path) -> dict:
    """One run of a peer's script in its venv (pyorc_run.py, openpiv_thesis.py, decode_floor.py in the peers';
    river_run.py in RIVeR's)."""
    py = peers_python(RIVER_VENV, RIVER) if script.startswith("river") else peers_python()
    wall, mem, text, cpu = timed([str(py), str(HERE / "peers" / script), str(job)])
    res = json.loads(text.strip().splitlines()[-1])
    return {"s": wall, "cpu": cpu, "mib": mem, "q": res.get("discharge_m3s"), "pairs": res.get("pairs"),
            "frames": res.get("frames")}


def sweep(c: dict, peers: list[str]) -> None:
    """The main settings of each of ``peers`` (pyorc, thesis, river) on one clip; the most accurate (smallest
    |error|) is written to SETTINGS, beside the other peers' settings already there."""
    truth = c["truth"]["discharge_m3s"]
    best = json.loads(SETTINGS.read_text()) if SETTINGS.is_file() else {}
    grids = {"pyorc": ("pyorc_run.py", PYORC_SWEEP, pyorc_job),
             "thesis": ("openpiv_thesis.py", THESIS_SWEEP, thesis_job),
             "river": ("river_run.py", RIVER_SWEEP, river_job)}
    for name in peers:
        script, grid, job = grids[name]
        print(f"\n== sweep of {name} on {c['name']} (true Q {truth:.4f} m³/s)")
        rows = []
        for setting in grid:
            try:
                r = run_peer(script, job(c, setting))
            except RuntimeError as e:
                print(f"{str(setting):18s} failed: {str(e)[-200:]}")
                continue
            if r["q"] is None:
                print(f"{str(setting):18s} no valid vector on the section")
                continue
            err = 100.0 * (r["q"] / truth - 1.0)
            rows.append((abs(err), setting))
            print(f"{str(setting):18s} {r['s']:7.2f} s {r['q']:9.4f} m³/s {err:+8.2f} %")
        best[name] = min(rows)[1]
        print(f"most accurate {name} setting: {best[name]}")
    SETTINGS.write_text(json.dumps({**best, "clip": c["name"]}))


def end_to_end(cs: list[dict], repeats: int, with_pyorc: bool, scratch: Path, reference: bool = True,
               river: bool = False) -> None:
    byte_compile()
    for c in cs:
        truth = c["truth"]["discharge_m3s"]
        err = lambda q: 100.0 * (q / truth - 1.0)  # noqa: E731
        best = best_settings()
        jobs = {"pyorc": ("pyorc_run.py", pyorc_job(c, best["pyorc"])),
                "thesis (OpenPIV rust)": ("openpiv_thesis.py", thesis_job(c, best["thesis"])),
                "decode only (PyAV)": ("decode_floor.py", c["dir"] / c["spec"].video_name)}
        if river:  # RIVeR's own workflow: every frame written as a JPEG file, then its PIV on every pair (slow)
            jobs["RIVeR"] = ("river_run.py", river_job(c, best["river"]))
        load0 = os.getloadavg()
        ref = run_fieldtool(c["dir"] / "full_all.toml", scratch) if reference else None
        runs: dict[str, list] = {"fieldtool": [], **{name: [] for name in jobs}}
        for _ in range(repeats):  # alternating: each repeat runs each contestant once, in turn
            runs["fieldtool"].append(run_fieldtool(c["dir"] / "noroi.toml", scratch))
            if with_pyorc:
                for name, (script, job) in jobs.items():
                    runs[name].append(run_peer(script, job))
        load1 = os.getloadavg()
        print(f"\n== {c['name']}: {c['truth']['n_frames']} frames, true Q {truth:.4f} m³/s; "
              f"{cores()} cores, load average {load0[0]:.2f} before, {load1[0]:.2f} after")
        print(f"peer settings (most accurate of the sweep on {json.loads(SETTINGS.read_text())['clip'] if SETTINGS.is_file() else 'the issue'}): "
              f"pyorc resolution {best['pyorc'][0]} m, window {best['pyorc'][1]} px; thesis window "
              f"{best['thesis'][0]} px, overlap {best['thesis'][0] // 2} px, s2n {best['thesis'][1]}"
              + (f"; RIVeR interrogation area {best['river']} -> {best['river'] // 2} px" if river else ""))
        print(f"{'contestant':34s} {'median s':>9s} {'runs s':>26s} {'CPU s':>7s} {'Q m³/s':>9s} {'error %':>8s} "
              f"{'pairs':>6s} {'peak MiB':>9s}")
        rows = ([("fieldtool full frame, all pairs", [ref])] if ref else []) + [(k, v) for k, v in runs.items() if v]
        med = {}
        for name, rs in rows:
            t = [r["s"] for r in rs]
            q = float(np.median([r["q"] for r in rs])) if rs[0]["q"] is not None else float("nan")
            med[name] = float(np.median(t))
            pairs = rs[-1]["pairs"]
            cpu = float(np.median([r["cpu"] for r in rs]))
            # a contestant without a discharge (the floor; a peer with no valid vector) shows none, not nan
            qs, es = (f"{q:9.4f}", f"{err(q):+8.2f}") if np.isfinite(q) else (f"{'-':>9s}", f"{'no Q':>8s}")
            print(f"{name:34s} {med[name]:9.2f} {' '.join(f'{v:.1f}' for v in t):>26s} {cpu:7.1f} {qs} {es} "
                  f"{'' if pairs is None else pairs:>6} {max(r['mib'] for r in rs):9d}")
        fq = float(np.median([r["q"] for r in runs["fieldtool"]]))
        if ref:
            print(f"fieldtool default vs full frame all pairs: {err(fq) - err(ref['q']):+.2f} percentage points of "
                  f"error")
        decoded = dict.fromkeys(r["frames"] for r in runs["fieldtool"])  # the runs' distinct counts, in order
        print(f"fieldtool default: {med['fieldtool']:.2f} s for a {c['truth']['n_frames'] / c['truth']['fps']:.0f} s "
              f"clip; frames decoded / in range: {', '.join(f'{d} / {n}' for d, n in decoded)}")
        for peer in ("pyorc", "thesis (OpenPIV rust)", "RIVeR"):
            if runs.get(peer):
                per = np.median([p["s"] / f["s"] for p, f in zip(runs[peer], runs["fieldtool"])])
                cpu_ratio = np.median([r["cpu"] for r in runs[peer]]) / np.median([r["cpu"] for r in runs["fieldtool"]])
                print(f"{peer} / fieldtool: {med[peer] / med['fieldtool']:.2f}x (ratio of medians), "
                      f"{per:.2f}x (median of per-run ratios), {cpu_ratio:.2f}x in CPU seconds")
        if runs["decode only (PyAV)"]:
            fl = runs["decode only (PyAV)"]
            print(f"fieldtool / decode-only floor: {med['fieldtool'] / med['decode only (PyAV)']:.2f}x "
                  f"({fl[-1]['frames']} frames decoded by PyAV)")


# --------------------------------------------------------------------------------------------- engines


def engines(runs: int, n_pairs: int, ens_pairs: int, scratch: Path) -> None:
    """pairs/s on 1920x1080 frames, window 32 / overlap 16: fieldtool, OpenPIV, ffpiv, RIVeR (alternating runs)."""
    sys.path.insert(0, str(HERE))
    import piv_vs_openpiv as pvo

    syn = pvo.syn
    frames = syn.clip(syn.rankine(pvo.W / 2, pvo.H / 2, rc=200, vmax=5.0), pvo.H, pvo.W, n_frames=n_pairs + 1,
                      density=0.03)
    stack = scratch / "ffpiv_frames.npy"
    np.save(stack, np.stack([f for _, f in frames]))
    clip = {"pairs": frames, "ensemble": [(k / 30.0, frames[k % len(frames)][1]) for k in range(ens_pairs + 1)]}
    table = list(pvo.ENGINES[:3]) + [pvo.ENGINES[4], pvo.ENGINES[5]]
    times = {name: [] for name, _, _ in table}
    times["ffpiv (numba) single pass"] = []
    rust = {"OpenPIV rust single pass": "single_pairs_per_s", "OpenPIV rust windef 64->32": "two_pass_pairs_per_s"}
    river = {"RIVeR piv_fftmulti 32->32": "32->32", "RIVeR piv_fftmulti 64->32": "64->32"}
    for name in (*rust, *river):
        times[name] = []
    py = peers_python()
    river_py = peers_python(RIVER_VENV, RIVER)
    for _ in range(runs):
        for name, fn, which in table:
            t0 = time.perf_counter()
            fn(clip[which])
            times[name].append((len(clip[which]) - 1) / (time.perf_counter() - t0))
        out = subprocess.run([str(py), str(HERE / "peers" / "ffpiv_rate.py"), str(stack), "32", "16"],
                             capture_output=True, text=True, check=True).stdout
        times["ffpiv (numba) single pass"].append(json.loads(out.strip().splitlines()[-1])["pairs_per_s"])
        out = subprocess.run([str(py), str(HERE / "peers" / "openpiv_rate.py"), str(stack), "rust"],
                             capture_output=True, text=True, check=True).stdout
        rates = json.loads(out.strip().splitlines()[-1])
        for name, key in rust.items():
            times[name].append(rates[key])
        # RIVeR: one pair a run (its 32 -> 32 call takes tens of seconds a pair on 1080p: river_rate.py says why)
        out = subprocess.run([str(river_py), str(HERE / "peers" / "river_rate.py"), str(stack), "1"],
                             capture_output=True, text=True, check=True).stdout
        rates = json.loads(out.strip().splitlines()[-1])
        for name, key in river.items():
            times[name].append(rates[key])
    print(f"\nEngines: 1920x1080, window 32, overlap 16, {n_pairs} pairs per call ({ens_pairs} for the ensemble), "
          f"{runs} alternating runs, {cores()} cores, load average {os.getloadavg()[0]:.2f} at the end")
    print(f"{'engine':36s} {'median pairs/s':>14s} {'runs':>28s} {'vs fieldtool single':>20s}")
    base = float(np.median(times["fieldtool single pass (mean)"]))
    for name, v in times.items():
        m = float(np.median(v))
        print(f"{name:36s} {m:14.3g} {' '.join(f'{x:.3g}' for x in v):>28s} {m / base:19.3g}x")
    for ours_name, peer in (("fieldtool single pass (mean)", "OpenPIV rust single pass"),
                            ("fieldtool 2 passes 64->32 (mean)", "OpenPIV rust windef 64->32"),
                            ("fieldtool 2 passes 64->32 (mean)", "RIVeR piv_fftmulti 64->32")):
        if ours_name in times and times[peer]:
            per_run = np.median(np.array(times[ours_name]) / np.array(times[peer]))
            print(f"{ours_name} / {peer}: {np.median(times[ours_name]) / np.median(times[peer]):.2f}x (ratio of "
                  f"medians), {per_run:.2f}x (median of per-run ratios)")


# --------------------------------------------------------------------------------------------- profile


def profile(c: dict, top: int) -> None:
    """cProfile of run_project on the clip: full frame + all pairs (before), then the defaults (after)."""
    import cProfile
    import io
    import pstats

    from fieldtool.run.pipeline import run_project
    from fieldtool.project.model import load_project

    for label, toml in (("before: region = full, all_pairs = true", "full_all.toml"), ("after: defaults", "noroi.toml")):
        proj = load_project(c["dir"] / toml)
        out = Path(tempfile.mkdtemp())
        pr = cProfile.Profile()
        t0 = time.perf_counter()
        pr.enable()
        run_project(proj, out)
        pr.disable()
        wall = time.perf_counter() - t0
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(top)
        print(f"\n== profile {c['name']}, {label}: {wall:.2f} s wall, load average {os.getloadavg()[0]:.2f}")
        print("\n".join(line for line in s.getvalue().splitlines() if line.strip())[:6000])
        shutil.rmtree(out, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default=os.path.join(tempfile.gettempdir(), "ft_time_to_q"), help="clip folder")
    ap.add_argument("--clips", default="720p_8s,1080p_30s,fast_1080p,4k_drone")
    ap.add_argument("--sweep", action="store_true", help="sweep the peers' settings on the first clip first")
    ap.add_argument("--sweep-peers", default="pyorc,thesis", help="the peers --sweep sweeps (pyorc, thesis, river)")
    ap.add_argument("--river", action="store_true", help="RIVeR's own workflow as a contestant too (slow)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-pyorc", action="store_true", help="fieldtool only")
    ap.add_argument("--no-reference", action="store_true", help="without the full-frame all-pairs fieldtool run")
    ap.add_argument("--engines", action="store_true", help="the engine table instead of end to end")
    ap.add_argument("--runs", type=int, default=3, help="engine table: alternating runs")
    ap.add_argument("--pairs", type=int, default=4, help="engine table: pairs per call")
    ap.add_argument("--ensemble-pairs", type=int, default=60, help="engine table: pairs of the ensemble clip")
    ap.add_argument("--profile", action="store_true", help="cProfile the first clip, before/after")
    ap.add_argument("--cores", type=int, help="run every contestant on this many cores only (default: all)")
    args = ap.parse_args()
    if args.cores is not None:
        try:
            limit_cores(args.cores)
        except ValueError as e:
            ap.error(str(e))
    root = Path(args.root)
    root.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix="ttq_"))
    try:
        if args.engines:
            engines(args.runs, args.pairs, args.ensemble_pairs, scratch)
            return
        cs = clips(root, args.clips.split(","))
        if args.profile:
            profile(cs[0], 25)
            return
        if args.sweep:
            sweep(cs[0], args.sweep_peers.split(","))
        end_to_end(cs, args.repeats, not args.no_pyorc, scratch, reference=not args.no_reference, river=args.river)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
