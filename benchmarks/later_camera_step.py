"""A camera knocked halfway through a slow clip: is it seen when the run uses every n-th frame?

    PYTHONPATH=. .venv/bin/python benchmarks/later_camera_step.py [--scenes far_bank_u0.15_f60_d6,...]
        [--shift-px 2] [--at 0.5] [--pace /tmp/pace_scenes] [--workdir /tmp/later_camera] [--results results]

The scenes are ``pace_scenes.py``'s (rendered there first: run it once). Each clip is copied with every frame from
``--at`` of its length on moved by ``--shift-px`` px to the right and down (the whole frame, as a tripod knocked
then left), re-encoded (mp4v, the clip's rate), and run with the defaults. The camera check looks at the first 20
frames (the camera was still) and, after the pass, at the patches around the GCPs that ``FrameSource.watch`` kept
every few frames of the rest (run/camera.py ``later``). Printed per scene: the frame step the run took, how many
later frames the check compared, whether it said the camera moved (``robust.camera.later.moved``, and the
warning), the grade, and the discharge's error against the truth integrated from the drawn profile.

Before / after a change: ``PYTHONPATH`` on a worktree of the commit before and ``--results before``, then on this
tree.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
from unseen_scenes import run_cli

SCENES = "far_bank_u0.15_f60_d6,far_bank_u0.15_f30_d6,oblique_u0.15_f60_d6,nadir_u0.15_f60_d6,oblique_u0.25_f60_d6"


def knock(src: Path, dst: Path, shift_px: float, at: float) -> None:
    """``src``'s clip into ``dst``, the frames from ``at`` of its length on moved by ``shift_px`` (x and y)."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("results", "before", "after", "river.mp4"))
    cap = cv2.VideoCapture(str(src / "river.mp4"))
    fps, n = cap.get(cv2.CAP_PROP_FPS), int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    out = cv2.VideoWriter(str(dst / "river.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    move = np.float32([[1, 0, shift_px], [0, 1, shift_px]])
    i = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        if i >= at * n:
            frame = cv2.warpAffine(frame, move, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        out.write(frame)
        i += 1
    cap.release()
    out.release()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--shift-px", type=float, default=2.0)
    ap.add_argument("--at", type=float, default=0.5, help="share of the clip after which the camera moved")
    ap.add_argument("--pace", default="/tmp/pace_scenes", help="pace_scenes.py's workdir")
    ap.add_argument("--workdir", default="/tmp/later_camera")
    ap.add_argument("--results", default="results")
    a = ap.parse_args()
    print(
        f"{'scene':<24} {'rc':>3} {'step':>4} {'later frames':>12} {'moved':<6} {'warned':<6} {'grade':<9} {'err %':>7}"
    )
    missed = 0
    for name in a.scenes.split(","):
        src, dst = Path(a.pace) / name, Path(a.workdir) / name
        if not (src / "river.mp4").exists():
            print(f"{name}: not rendered; run pace_scenes.py first", file=sys.stderr)
            return 2
        if not (dst / "river.mp4").exists():
            knock(src, dst, a.shift_px, a.at)
        q_true = json.loads((dst / "truth.json").read_text())["discharge_m3s"]
        rc, res, _ = run_cli(dst / "project.toml", dst / a.results)
        rob = (res or {}).get("robust") or {}
        later = (rob.get("camera") or {}).get("later") or {}
        step = (rob.get("gates") or {}).get("frame_step", "-")
        warned = any("moved later" in w for w in (res or {}).get("warnings", []))
        q = (res or {}).get("discharge_m3s")
        err = "-" if q is None else f"{100 * (q - q_true) / q_true:+.1f}"
        grade = ((res or {}).get("quality") or {}).get("grade")
        moved = bool(later.get("moved"))
        missed += not moved
        print(
            f"{name:<24} {rc:>3} {step!s:>4} {later.get('frames', '-')!s:>12} {moved!s:<6} {warned!s:<6} "
            f"{grade!s:<9} {err:>7}",
            flush=True,
        )
    print(f"camera's later move missed in {missed} of {len(a.scenes.split(','))} clips")
    return 0


if __name__ == "__main__":
    sys.exit(main())
