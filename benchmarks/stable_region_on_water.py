"""What a stabilisation rectangle on the water costs, and whether the validation layer refuses it.

Renders the shaky oblique scene (exact truth), runs it with the generator's stable regions (on the
banks), then with one region replaced by a rectangle of the same size on the water: across the
section of interest (refused by `fieldtool.project.validation`: measured here with the check bypassed) and on
the water upstream of the section (not across it).

    nice -n 10 .venv/bin/python benchmarks/stable_region_on_water.py [--duration 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=2.0)
    args = ap.parse_args()
    import fieldtool.project.validation as V
    from fieldtool.run import pipeline
    from fieldtool.errors import FieldToolError
    from fieldtool.project.model import load_project
    from fieldtool.synthetic import presets, render_scene

    tmp = Path(tempfile.mkdtemp(prefix="stab_water_"))
    truth = render_scene(presets.get("oblique", duration_s=args.duration, shake=True), tmp / "scene")
    proj = load_project(truth.project_path)
    regions = proj.stabilize.regions_px
    (a, b) = proj.section.points_px
    w = 60.0  # a 120 x 60 px rectangle (the generator's bank strips are much larger)
    h = 30.0
    mid = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2]
    across = [mid[0] - w, mid[1] - h, mid[0] + w, mid[1] + h]
    # upstream on the water: the middle of the ROI's half away from the section, kept off the section line
    x0, y0, x1, y1 = proj.roi.rect_px
    cand = [[cx - w, cy - h, cx + w, cy + h] for cx in (x0 + (x1 - x0) * f for f in (0.3, 0.5, 0.7))
            for cy in (y0 + (y1 - y0) * g for g in (0.25, 0.75))]
    off = next(r for r in cand if not V._rects_intersect_segment(r, a, b))

    def q(regs, bypass=False):
        proj.stabilize.regions_px = regs
        probs = [p for p in V.validate(proj) if p.severity == "error"]
        real_check = V.check
        if bypass:
            V.check = lambda *a, **k: []
        try:
            r = pipeline.run_project(proj, None)
        except FieldToolError as e:
            return None, [str(p) for p in probs] + [f"(stabiliser: {e})"]
        finally:
            V.check = real_check
        err = 100 * (r.discharge.discharge_m3s - truth.discharge_m3s) / truth.discharge_m3s
        return err, [str(p) for p in probs]

    rows = [("banks (generator's regions)", regions, False),
            ("one region across the section", [across] + regions[1:], True),
            ("one region on the water, off the section", [off] + regions[1:], True)]
    print(f"truth Q = {truth.discharge_m3s:.3f} m3/s; load average {os.getloadavg()[0]:.1f}")
    for label, regs, bypass in rows:
        err, probs = q(regs, bypass)
        e = "refused " if err is None else f"{err:+6.1f} %"
        print(f"{label:45s} Q error {e}   validation: {probs[0] if probs else 'accepted'}"
              + (f"; {probs[-1]}" if len(probs) > 1 else ""))


if __name__ == "__main__":
    main()
