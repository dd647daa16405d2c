"""Several sections: discharge error of each of three sections (X = -1.5, 0, +1.5 m around the surveyed one) on
one velocity field, with their mean, std and CV, on the demo scene, the nadir scene and an oblique scene with a
1.2 m island.

    .venv/bin/python benchmarks/sections_accuracy.py --duration 5
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from fieldtool.run.pipeline import run_project
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene

SCENES = [("oblique (demo)", "oblique", {}), ("nadir", "nadir", {}),
          ("oblique + island", "oblique", {"river__island_m": (3.5, 4.7)})]


def section_px(truth, x_m: float) -> list:
    r = truth.spec.river
    pts = np.array([[x_m, r.y_left_edge, r.level_m], [x_m, r.y_right_edge, r.level_m]])
    px, _ = cv2.projectPoints(pts, cv2.Rodrigues(truth.R)[0], truth.t, truth.K, truth.dist)
    return px.reshape(2, 2).tolist()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--duration", type=float, default=5.0)
    a = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}")
    print("| scene | X = -1.5 m | X = 0 (main) | X = +1.5 m | mean | std | CV |")
    print("|---|---|---|---|---|---|---|")
    for label, name, kw in SCENES:
        with tempfile.TemporaryDirectory() as d:
            t = render_scene(presets.get(name, duration_s=a.duration, **kw), Path(d))
            p = load_project(t.project_path)
            xs = t.spec.river.x_section_m
            p.sections = [{"name": "up", "points_px": section_px(t, xs - 1.5)},
                          {"name": "down", "points_px": section_px(t, xs + 1.5)}]
            r = run_project(p, None)
            e = {s["name"]: s for s in r.sections}
            err = {k: 100 * (v["discharge_m3s"] / t.discharge_m3s - 1) if "discharge_m3s" in v else float("nan")
                   for k, v in e.items()}
            sm = r.summary()["sections_summary"] or {}
            print(f"| {label} | {err['up']:+.2f} % | {err['main']:+.2f} % | {err['down']:+.2f} % | "
                  f"{100 * (sm.get('mean_m3s', np.nan) / t.discharge_m3s - 1):+.2f} % | {sm.get('std_m3s', np.nan):.3f} m³/s | "
                  f"{100 * sm.get('cv', np.nan):.1f} % |", flush=True)
            sys.stdout.flush()


if __name__ == "__main__":
    main()
