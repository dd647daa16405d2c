"""The weak-signal plan's temporal mean, on and off: what it does to a drawn scene's PIV (stop 55's g079 lead).

    PYTHONPATH=. .venv/bin/python benchmarks/temporal_mean_probe.py /tmp/combo_scenes/g079 [--gaps 3,6,9]
    PYTHONPATH=. .venv/bin/python benchmarks/temporal_mean_probe.py --selfcheck /tmp/combo_scenes/g079 \
        /tmp/combo_scenes/c230

Each scene folder is one of benchmarks/combo_scenes.py's (project.toml, truth.json). Where the clip check's plan
averages frames in time (processing/lowlight.py ``temporal_mean``, ``gates.denoise_half``), the scene runs with the
plan as it is and with the mean left out (the run's ClipCheck patched in its own process: no mean, no frame gap
raised to the mean's window), at each ``--gaps`` (``piv.frame_gap``; none: the run's own choice). Printed per run:
the discharge's error, PIV's and STIV's, the grade and PIV's velocity per subsection (m/s).

``--selfcheck``: instead, the scores that ``selfcheck.choose`` gives the first frames' field with the mean and
without it (the check's own frames and parameters), and which it would keep; the run stops after the clip check.
Stop 55: g079 0.739 with against 0.749 without (kept: without; PIV +27.1 -> +6.6 %); c230 0.30 against 0.50 (kept:
without; -0.3 -> -10.7 %, outside its interval), so no such rule was landed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import tomlkit

REPO = Path(__file__).resolve().parent.parent

# the run in a process of its own, its clip check patched by MODE: "mean" (as it is), "no_mean", "selfcheck"
RUNNER = r"""
import copy, json, os, sys
import numpy as np
from fieldtool.cli import main as cli
cli.build_parser()
cli.load_measure()
from fieldtool.processing import selfcheck, surface
from fieldtool.run import clip_check, velocimetry
mode = os.environ["PROBE_MODE"]
if mode == "no_mean":
    clip_check.ClipCheck.after = lambda self, frames, want: frames
    clip_check.ClipCheck.std_want = lambda self, want: want
    clip_check.ClipCheck.gap = lambda self, params: params
elif mode == "selfcheck":
    check = clip_check.check
    def probe(head, roi, n_clip, params=None, mask=None, standardize=True, user_gap=None, no_step=None, fps=None):
        out = check(head, roi, n_clip, params, mask, standardize, user_gap, no_step, fps)
        g = out.gates
        if params is None or not standardize or not g.denoise_half:
            print("PROBE " + json.dumps(None))
            raise SystemExit(0)
        got = [f for f in head if f.image is not None][:: max(g.step, 1)]
        frames = [np.asarray(f.image) for f in got]
        dt = float(np.median(np.diff([f.t_s for f in got]))) or 1 / 30
        def make(gv):
            def run():
                c = clip_check.ClipCheck(out.stats, gv, fps)
                fr = surface.standardize(c.before(list(zip([f.t_s for f in got], frames))), roi,
                                         half=surface.HALF_WINDOW, shrink=gv.shrink)
                return [f for _, f in c.after(fr, None)], c.params(params, True)
            return run
        plain = copy.deepcopy(g)
        plain.denoise_half = 0
        best, scores = selfcheck.choose({"mean": make(g), "no_mean": make(plain)}, dt, roi, mask,
                                        gap=clip_check.SELF_GAP)
        print("PROBE " + json.dumps({"kept": best, "scores": [s.to_dict() for s in scores]}))
        raise SystemExit(0)
    velocimetry.clip_check.check = probe
ap = cli.build_parser()
args = ap.parse_args(sys.argv[1:])
sys.exit(args.func(args))
"""


def run(scene: Path, mode: str, gap: int | None, out: Path) -> subprocess.CompletedProcess:
    doc = tomlkit.parse((scene / "project.toml").read_text())
    if gap is not None:
        doc["piv"]["frame_gap"] = gap
    project = scene / f"probe_{mode}_{gap}.toml"  # beside the scene: its paths are relative to the project
    project.write_text(tomlkit.dumps(doc))
    try:
        env = dict(os.environ, PYTHONPATH=str(REPO), PROBE_MODE=mode)
        cmd = [sys.executable, "-c", RUNNER, "run", str(project), "--out", str(out), "--quiet"]
        return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    finally:
        project.unlink()


def err(q, truth: float) -> str:
    return "-" if q is None else f"{100.0 * (q / truth - 1.0):+.1f} %"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--gaps", default="", help="piv.frame_gap values, comma-separated (default: the run's own)")
    ap.add_argument("--selfcheck", action="store_true", help="the self-check's scores with and without the mean")
    args = ap.parse_args()
    gaps = [int(g) for g in args.gaps.split(",") if g] or [None]
    for scene in args.scenes:
        truth = json.loads((scene / "truth.json").read_text())["discharge_m3s"]
        with tempfile.TemporaryDirectory(prefix="temporal_mean_probe_") as tmp:
            if args.selfcheck:
                p = run(scene, "selfcheck", None, Path(tmp) / "out")
                line = next((x for x in p.stdout.splitlines() if x.startswith("PROBE ")), None)
                said = "no result" if line is None else json.loads(line[6:])
                if isinstance(said, dict):
                    sc = " ".join(f"{s['name']} {s['score']}" for s in said["scores"])
                    said = f"kept {said['kept']}: {sc}"
                print(f"{scene.name:8s} {said or 'the plan takes no temporal mean'}", flush=True)
                continue
            for gap in gaps:
                for mode in ("mean", "no_mean"):
                    out = Path(tmp) / f"{mode}_{gap}"
                    p = run(scene, mode, gap, out)
                    try:
                        r = json.loads((out / "result.json").read_text())
                    except OSError:
                        print(f"{scene.name:8s} gap {gap} {mode:8s} exit {p.returncode}: {p.stderr.strip()[-200:]}")
                        continue
                    st = r.get("stiv") or {}
                    frames = (r.get("robust") or {}).get("gates", {}).get("denoise_frames")
                    plan = "mean left out" if mode == "no_mean" else f"mean over {frames} frames"
                    v = [None if x is None else round(x, 2) for x in st.get("piv_velocity_ms") or []]
                    print(
                        f"{scene.name:8s} gap {gap} ({plan}) Q {err(r['discharge_m3s'], truth)}"
                        f" PIV {err(st.get('discharge_piv_m3s', r['discharge_m3s']), truth)}"
                        f" STIV {err(st.get('discharge_m3s'), truth)} {r['quality']['grade']} | PIV m/s {v}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
