"""Lens from GCPs (no checkerboard): discharge error on the strong-barrel preset, uncorrected vs the lens
fitted from 8 GCPs vs the true lens, and the fitted focal length's error, over a few seeds.

    .venv/bin/python benchmarks/lens_from_gcps.py --seeds 3 --duration 3
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

from fieldtool.run.pipeline import run_project
from fieldtool.processing.calibration import LensModel, save_calibration
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=3.0)
    a = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}")
    print("| seed | uncorrected | lens from 8 GCPs | true lens | fx error | k1 fitted (true -0.35) |")
    print("|---|---|---|---|---|---|")
    for seed in range(a.seeds):
        with tempfile.TemporaryDirectory() as d:
            t = render_scene(presets.get("oblique", lens_gcps=True, duration_s=a.duration, seed=seed,
                                         checkerboard_frames=2), Path(d))
            q = t.discharge_m3s

            def err(p) -> float:
                return 100 * (run_project(p, None).discharge.discharge_m3s / q - 1)

            base = load_project(t.project_path)
            base.calibration.checkerboard_video = ""
            e_raw = err(base)
            fit = load_project(t.project_path)
            fit.calibration.checkerboard_video = ""
            rng = np.random.default_rng(seed)
            fit.ortho.method, fit.ortho.fit_lens = "pose", True
            fit.ortho.gcp_px = (t.gcp_px + rng.normal(0, 0.3, t.gcp_px.shape)).tolist()
            fit.ortho.gcp_world_m = t.gcp_world_m.tolist()
            r = run_project(fit, None)
            e_fit = 100 * (r.discharge.discharge_m3s / q - 1)
            lf = r.mapping.details["lens_from_gcps"]
            save_calibration(LensModel(t.K, t.dist, (t.spec.camera.width_px, t.spec.camera.height_px)), Path(d) / "lens.toml")
            base.calibration.path = "lens.toml"
            e_true = err(base)
            print(f"| {seed} | {e_raw:+.2f} % | {e_fit:+.2f} % | {e_true:+.2f} % | "
                  f"{100 * (lf['f_px'] / t.K[0, 0] - 1):+.2f} % | {lf['k1']:+.3f} |")


if __name__ == "__main__":
    main()
