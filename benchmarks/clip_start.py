"""A phone clip's first second: exposure settling, focus hunting, a fade from black.

    PYTHONPATH=. .venv/bin/python benchmarks/clip_start.py [--scenes oblique_s0_d6,nadir_s0_d6,far_bank_s0_d6]
        [--unseen /tmp/unseen_scenes] [--workdir /tmp/clip_start] [--results results]

The run looks at the clip's first frames for its settings (run/clip_check.py: the gates, the water's pace, the
camera check; processing/planning.py: the first look that plans the frame gap), and a phone's first frames are
often its worst. Each scene of ``unseen_scenes.py`` (rendered there first: run it once) is re-encoded (mp4v, its
rate) four ways, the rest of the clip untouched:

* ``identity``: re-encoded only (the baseline of the re-encoding's own loss);
* ``exposure``: the first 30 frames brightened by a gain of 2.2 decaying to 1 (1 + 1.2 exp(-i / 6)), clipped at
  255, as an auto-exposure settles;
* ``focus``: the first 20 frames blurred (Gaussian, 4 px shrinking to 0), as an autofocus hunts;
* ``black``: the first 10 frames faded in from black.

Printed per clip: as ``unseen_scenes.py`` (error against the truth integrated from the drawn profile, grade,
interval, pass rule), the frame step the run took, and how many first frames its first look skipped
(``robust.plan.frames_skipped``).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
from unseen_scenes import HEAD, derived, derived_args, fmt, row, run_cli

KINDS = ("identity", "exposure", "focus", "black")


def transformed(frame: np.ndarray, i: int, kind: str) -> np.ndarray:
    """Frame ``i`` of the clip as ``kind`` films it."""
    if kind == "exposure" and i < 30:
        g = 1.0 + 1.2 * np.exp(-i / 6.0)
        return np.clip(frame.astype(np.float32) * g, 0, 255).astype(np.uint8)
    if kind == "focus" and i < 20 and 4.0 * (1 - i / 20) > 0.3:
        return cv2.GaussianBlur(frame, (0, 0), 4.0 * (1 - i / 20))
    if kind == "black" and i < 10:
        return (frame * (i / 10)).astype(np.uint8)
    return frame


def make(src: Path, dst: Path, kind: str) -> None:
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("results*", "before", "after", "river.mp4"))
    cap = cv2.VideoCapture(str(src / "river.mp4"))
    fps, w, h = cap.get(cv2.CAP_PROP_FPS), int(cap.get(3)), int(cap.get(4))
    out = cv2.VideoWriter(str(dst / "river.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    i = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        out.write(transformed(frame, i, kind))
        i += 1
    cap.release()
    out.release()


def main() -> int:
    ap = derived_args(__doc__, "oblique_s0_d6,nadir_s0_d6,far_bank_s0_d6", "/tmp/clip_start")
    a = ap.parse_args()
    print(HEAD + f" {'step':>4} {'skipped':>7}", flush=True)
    rows = []
    for name, kind, d, q_true in derived(a, KINDS, make, marker="river.mp4"):
        rc, res, dt = run_cli(d / "project.toml", d / a.results)
        r = row(f"{name} {kind}", 0, rc, res, q_true, dt)
        rob = (res or {}).get("robust") or {}
        step = (rob.get("gates") or {}).get("frame_step", "-")
        skipped = (rob.get("plan") or {}).get("frames_skipped", "-")
        rows.append(r)
        print(fmt(r, f" {step!s:>4} {skipped!s:>7}"), flush=True)
    for kind in KINDS:
        mine = [r for r in rows if r["preset"].endswith(" " + kind)]
        errs = [abs(r["err"]) for r in mine if r["err"] is not None]
        print(
            f"{kind}: {sum(r['pass'] for r in mine)}/{len(mine)} pass, max |error| {max(errs, default=float('nan')):.1f} %"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
