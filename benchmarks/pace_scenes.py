"""The water's pace against the frame rate: error, grade and frame step per view x surface speed x frame rate.

    PYTHONPATH=. .venv/bin/python benchmarks/pace_scenes.py [--views oblique,nadir,far_bank]
        [--speeds 0.15,0.25,0.5] [--fps 30,60] [--duration 6] [--workdir /tmp/pace_scenes] [--results results]
    # floods on a station camera: fast water at low frame rates
    PYTHONPATH=. .venv/bin/python benchmarks/pace_scenes.py --speeds 2,5,7 --fps 5,10 --duration 10 \
        --workdir /tmp/flood_scenes

Every preset draws a river of 1.2-3.2 m/s at 25-30 fps. These scenes draw the base views with the surface
velocity at the deepest point set to each speed (``river__u_max_ms``) and filmed at each frame rate, the seed
varying with the scene: slow water at high frame rates (the defaults) moves a fraction of a pixel a frame, fast
water at low frame rates (a station camera recording 5 or 10 frames a second in a flood) up to a hundred. Each is rendered once into WORKDIR/<view>_u<speed>_f<fps>_d<duration>/ (kept) and run
through ``fieldtool run`` as ``unseen_scenes.py`` runs its scenes (same columns, same pass rule: a good grade
must be within 5 %; otherwise the truth inside a 95 % interval no wider than +-25 %), with the frame step the run
took and the water's decorrelation time it measured (``robust.gates.frame_step``, ``robust.surface_change``).

Before / after a change: run it once with ``PYTHONPATH`` on a worktree of the commit before and
``--results before`` (a tree without ``robust.surface_change`` prints "-" there), then on this tree.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from unseen_scenes import HEAD, fmt, row, run_cli

from fieldtool.synthetic import presets, render_scene


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default="oblique,nadir,far_bank")
    ap.add_argument("--speeds", default="0.15,0.25,0.5", help="surface velocity at the deepest point, m/s")
    ap.add_argument("--fps", default="30,60", help="frames per second")
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--workdir", default="/tmp/pace_scenes")
    ap.add_argument("--results", default="results", help="results folder inside each scene's (keep before/after)")
    a = ap.parse_args()
    rows = []
    print(HEAD + f" {'step':>4} {'tau frames':>10} {'tau s':>6}", flush=True)
    seed = 0
    for view in a.views.split(","):
        for u in [float(s) for s in a.speeds.split(",")]:
            for fps in [float(s) for s in a.fps.split(",")]:
                d = Path(a.workdir) / f"{view}_u{u:g}_f{fps:g}_d{a.duration:g}"
                if not (d / "truth.json").exists():
                    spec = presets.get(view, seed=seed, duration_s=a.duration, fps=fps, river__u_max_ms=u)
                    render_scene(spec, d)
                seed += 1
                q_true = json.loads((d / "truth.json").read_text())["discharge_m3s"]
                rc, res, dt = run_cli(d / "project.toml", d / a.results)
                r = row(f"{view} {u:g} m/s {fps:g}", seed - 1, rc, res, q_true, dt)
                rob = (res or {}).get("robust") or {}
                change = rob.get("surface_change") or {}
                step = (rob.get("gates") or {}).get("frame_step", "-")
                tau, tau_s = change.get("tau_frames"), change.get("tau_s")
                rows.append(r)
                tau_txt = "-" if tau is None else f"{tau:.1f}"
                tau_s_txt = "-" if tau_s is None else f"{tau_s:.2f}"
                extra = f" {step!s:>4} {tau_txt:>10} {tau_s_txt:>6}"
                print(fmt(r, extra), flush=True)
    n_fail = sum(not r["pass"] for r in rows)
    good = [r for r in rows if r["grade"] == "good"]
    print(
        f"{len(rows) - n_fail}/{len(rows)} pass; graded good {len(good)}, "
        f"max |error| of those {max((abs(r['err']) for r in good), default=float('nan')):.2f} %; "
        f"exit 3 (unusable) {sum(r['rc'] == 3 for r in rows)}"
    )
    return 1 if n_fail else 0


if __name__ == "__main__":
    sys.exit(main())
