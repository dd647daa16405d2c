"""Where a run's CPU goes, and the fastest wall time that CPU allows: is ≥ 3× pyorc reachable without less work?

    PYTHONPATH=. .venv/bin/python benchmarks/cpu_budget.py --clips 720p_8s,1080p_30s,fast_1080p,4k_drone

Per clip (the clips of ``time_to_q.py``, rendered there once), in alternating runs (``--repeats``, medians):

* ``fieldtool run`` with the defaults, in a process that reports its own CPU (user + system, every thread) apart
  from its children's: the figure processes (``plots.prerender``), waited by the run before it exits;
* pyorc at its most accurate setting (``peer_settings.json``) and the decode-only floor, as ``time_to_q.py``
  runs them (their CPU: the process and its children).

Printed: wall s; the run's CPU s and the figures' CPU s; the floor's wall and CPU s; and a bound on this host
(the cores it may use: ``time_to_q.cores()``). A process cannot finish in less wall time than its CPU over the
cores, so ``run CPU / cores`` is the fastest wall time the run's work allows, even were the figures free and every
stage perfectly parallel; ``pyorc wall / that`` is the best pyorc ratio without cutting the run's work. Where that
bound is below 3, ≥ 3× pyorc needs less CPU in the run (decoding, standardising, correlating), not more overlap.

``--ablate``: what two of the defaults cost, the figures (every PNG of the run, drawn in its figure process) and
STIV's cross-check (``[stiv] enabled``), in alternating runs of four variants of the same project (default, no STIV,
no figures, neither) beside pyorc: wall s, CPU s (the run and its children) and pyorc / variant per clip. Neither
changes the discharge (STIV only checks the PIV unless ``[section] velocity_source`` says otherwise); the figures
are left out by NO_FIGURES below, in the benchmark's process only: fieldtool has no such switch.

    PYTHONPATH=. .venv/bin/python benchmarks/cpu_budget.py --ablate --clips 720p_8s,fast_1080p --repeats 5

``--trees A,B``: the four variants of each source tree, all alternating (each row named by its tree's folder).
Stop 47 ran this repository against a worktree with stop 46's decoding ahead (``experiments/decode_ahead.diff``,
not landed), to see whether decoding ahead pays once the figures leave the second core free:

    git worktree add /tmp/ahead HEAD && git -C /tmp/ahead apply benchmarks/experiments/decode_ahead.diff
    PYTHONPATH=. .venv/bin/python benchmarks/cpu_budget.py --ablate --trees .,/tmp/ahead --clips 720p_8s,fast_1080p
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tomlkit

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import time_to_q as ttq  # noqa: E402

# the run in a process of its own that prints its CPU and its children's once its exit handlers run (the CLI ends
# with os._exit after atexit, and the figure processes are waited by then)
WRAPPER = """
import atexit, json, resource, runpy, sys
def report():
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    print("CPU " + json.dumps({"run": s.ru_utime + s.ru_stime, "children": c.ru_utime + c.ru_stime}), flush=True)
atexit.register(report)
sys.argv = ["fieldtool"] + sys.argv[1:]
runpy.run_module("fieldtool.cli.main", run_name="__main__")
"""


# --ablate's run without figures: no figure process, and none of the run's figures drawn in its own process
NO_FIGURES = """
import types
from fieldtool.plots import prerender
from fieldtool.run import outputs
import fieldtool.writers as writers
prerender.start = lambda: None
outputs.start_prerender = lambda *a, **k: None
outputs._write_figures = lambda *a, **k: None
writers._figures = lambda: types.SimpleNamespace(write_profile=lambda *a: (None, None), write_gcp=lambda *a: None)
"""


def run_fieldtool(toml: Path, scratch: Path, figures: bool = True, tree: Path = ttq.REPO) -> dict:
    """time_to_q.py's run, through WRAPPER: its wall time and discharge, the run's CPU and the figures'.
    ``figures=False``: through NO_FIGURES too (``--ablate``); ``tree``: the source tree run (this repository's)."""
    launcher = ("-c", WRAPPER if figures else NO_FIGURES + WRAPPER)
    r = ttq.run_fieldtool(toml, scratch, launcher=launcher, tree=tree)
    cpu = json.loads(next(line for line in r["stdout"].splitlines() if line.startswith("CPU "))[4:])
    return {**r, "run_cpu": cpu["run"], "fig_cpu": cpu["children"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default=os.path.join(tempfile.gettempdir(), "ft_time_to_q"), help="clip folder")
    ap.add_argument("--clips", default="720p_8s,1080p_30s,fast_1080p,4k_drone")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ablate", action="store_true", help="the cost of the figures and of STIV (see above)")
    ap.add_argument("--trees", default="", help="--ablate: source trees to alternate, comma-separated (see above)")
    args = ap.parse_args()
    trees = [Path(t).resolve() for t in args.trees.split(",") if t] or None
    for tree in trees or []:
        if not (tree / "fieldtool").is_dir():
            ap.error(f"--trees: {tree}: no fieldtool package there; give checkouts of this repository")
    for tree in trees or [ttq.REPO]:
        ttq.byte_compile(tree)
    if args.ablate:
        ablate(Path(args.root), args.clips.split(","), args.repeats, trees)
        return
    cores = ttq.cores()
    rows = []
    best = ttq.best_settings()
    with tempfile.TemporaryDirectory(prefix="cpu_budget_") as tmp:
        scratch = Path(tmp)
        for c in ttq.clips(Path(args.root), args.clips.split(",")):
            pyorc_job = ttq.pyorc_job(c, best["pyorc"])
            video = c["dir"] / c["spec"].video_name
            ft, py, fl = [], [], []
            for _ in range(args.repeats):  # alternating
                ft.append(run_fieldtool(c["dir"] / "noroi.toml", scratch))
                py.append(ttq.run_peer("pyorc_run.py", pyorc_job))
                fl.append(ttq.run_peer("decode_floor.py", video))

            def med(runs: list[dict], key: str) -> float:
                return float(np.median([r[key] for r in runs]))

            truth = c["truth"]["discharge_m3s"]
            row = {
                "clip": c["name"],
                "ft_s": med(ft, "s"),
                "run_cpu": med(ft, "run_cpu"),
                "fig_cpu": med(ft, "fig_cpu"),
                "pyorc_s": med(py, "s"),
                "floor_s": med(fl, "s"),
                "floor_cpu": med(fl, "cpu"),
                "err": 100.0 * (med(ft, "q") / truth - 1.0),
            }
            row["bound_s"] = row["run_cpu"] / cores
            rows.append(row)
            walls = {k: " ".join(f"{r['s']:.2f}" for r in v) for k, v in (("ft", ft), ("py", py), ("fl", fl))}
            print(f"{c['name']}: fieldtool {walls['ft']} s, pyorc {walls['py']} s, floor {walls['fl']} s")
    print(
        f"\nCPU budget, {cores} cores, {args.repeats} alternating runs, medians, load average "
        f"{os.getloadavg()[0]:.2f} at the end; pyorc at {best['pyorc'][0]} m / {best['pyorc'][1]} px"
    )
    print(
        "| clip | fieldtool s (err) | run CPU s | figures CPU s | floor s (CPU s) | pyorc s | pyorc / ft "
        "| run CPU / cores | best pyorc ratio |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['clip']} | {r['ft_s']:.2f} ({r['err']:+.2f} %) | {r['run_cpu']:.2f} | {r['fig_cpu']:.2f} | "
            f"{r['floor_s']:.2f} ({r['floor_cpu']:.2f}) | {r['pyorc_s']:.2f} | {r['pyorc_s'] / r['ft_s']:.2f}× | "
            f"{r['bound_s']:.2f} | {r['pyorc_s'] / r['bound_s']:.2f}× |"
        )


#: --ablate's variants: (name, STIV on, figures on)
VARIANTS = (("default", True, True), ("no STIV", False, True), ("no figures", True, False), ("neither", False, False))


def no_stiv(toml: Path) -> Path:
    """A copy of ``toml`` beside it with ``[stiv] enabled = false`` (tomlkit: the rest as written)."""
    doc = tomlkit.parse(toml.read_text())
    doc["stiv"]["enabled"] = False  # type: ignore[index]
    out = toml.with_name(f"{toml.stem}_nostiv.toml")
    out.write_text(tomlkit.dumps(doc))
    return out


def ablate(root: Path, names: list[str], repeats: int, trees: list[Path] | None = None) -> None:
    """The four VARIANTS and pyorc, alternating, per clip; a table of medians. ``trees``: source trees of
    fieldtool (``PYTHONPATH``) whose variants alternate too (default: this repository's)."""
    best = ttq.best_settings()
    rows = []
    named = [t.name for t in trees or []]  # rows named by the trees' folders, or their paths where alike
    label = {t: f"{t.name if named.count(t.name) == 1 else t} " if len(named) > 1 else "" for t in trees or [ttq.REPO]}
    variants = [(label[t] + name, t, stiv_on, figures) for t in label for name, stiv_on, figures in VARIANTS]
    with tempfile.TemporaryDirectory(prefix="cpu_budget_") as tmp:
        scratch = Path(tmp)
        for c in ttq.clips(root, names):
            tomls = {True: c["dir"] / "noroi.toml", False: no_stiv(c["dir"] / "noroi.toml")}
            job = ttq.pyorc_job(c, best["pyorc"])
            runs: dict[str, list[dict]] = {v[0]: [] for v in variants} | {"pyorc": []}
            for _ in range(repeats):  # alternating
                for name, tree, stiv_on, figures in variants:
                    runs[name].append(run_fieldtool(tomls[stiv_on], scratch, figures=figures, tree=tree))
                runs["pyorc"].append(ttq.run_peer("pyorc_run.py", job))
            py = float(np.median([r["s"] for r in runs["pyorc"]]))
            for name, *_ in variants:
                rs = runs[name]
                wall = float(np.median([r["s"] for r in rs]))
                cpu = float(np.median([r["run_cpu"] + r["fig_cpu"] for r in rs]))
                qs = sorted({round(r["q"], 6) for r in rs})
                rows.append((c["name"], name, wall, cpu, py, qs))
                print(f"{c['name']} {name}: " + " ".join(f"{r['s']:.2f}" for r in rs) + f" s; Q {qs}")
            print(f"{c['name']} pyorc: " + " ".join(f"{r['s']:.2f}" for r in runs["pyorc"]) + " s")
    print(
        f"\nThe cost of the figures and of STIV, {ttq.cores()} cores, {repeats} alternating runs, medians, load "
        f"average {os.getloadavg()[0]:.2f} at the end; pyorc at {best['pyorc'][0]} m / {best['pyorc'][1]} px"
    )
    print("| clip | variant | wall s | CPU s (with children) | pyorc s | pyorc / variant | Q m³/s |")
    print("|---|---|---|---|---|---|---|")
    for clip, name, wall, cpu, py, qs in rows:
        q = ", ".join(f"{x:.4f}" for x in qs)
        print(f"| {clip} | {name} | {wall:.2f} | {cpu:.2f} | {py:.2f} | {py / wall:.2f}× | {q} |")


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    print(f"({time.perf_counter() - t0:.0f} s)")
