"""Automatic water line on synthetic scenes: level error of `water_level.method = "waterline"` (edges found
in the clip along the section's points lengthened by 40 %), its 1-sigma, per scene and seed.

    .venv/bin/python benchmarks/waterline_accuracy.py --seeds 2 --duration 2
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from fieldtool.errors import FieldToolError
from fieldtool.pipeline import level_and_mapping, load_inputs
from fieldtool.project import load_project
from fieldtool.synthetic import presets, render_scene

SCENES = [("oblique", {}), ("nadir", {}), ("far_bank", {}), ("oblique", {"glints": True}), ("nadir", {"glints": True})]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--duration", type=float, default=2.0)
    a = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}")
    print("| scene | seed | level error | 1-sigma | edges moved to the mean-image step |")
    print("|---|---|---|---|---|")
    for name, kw in SCENES:
        for seed in range(a.seeds):
            with tempfile.TemporaryDirectory() as d:
                t = render_scene(presets.get(name, duration_s=a.duration, seed=seed, **kw), Path(d))
                p = load_project(t.project_path)
                p.water_level.method = "waterline"
                label = name + (" + glints" if kw else "")
                try:
                    lv, _ = level_and_mapping(p, load_inputs(p))
                except FieldToolError as e:
                    print(f"| {label} | {seed} | refused: {e} | | |")
                    continue
                print(f"| {label} | {seed} | {100 * (lv.level_m - t.water_level_m):+.2f} cm | "
                      f"{100 * lv.uncertainty_m:.2f} cm | {lv.details.get('refined_on_mean_image', '')} |")


if __name__ == "__main__":
    main()
