"""Automatic water line on the real Geul clip (no truth): the edges found along a search line across the
river, their 1-sigma, the width they give on the authors' water plane (z_0, pose from the 6 GCPs and their
lens), and a picture for docs/.

    .venv/bin/python benchmarks/waterline_geul.py --png docs/waterline_geul.png

The Geul data hold no cross-section, so no level can be derived from the width here; with a surveyed
section, `water_level.method = "waterline"` turns the same edges into a level (tests/test_waterline.py).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from fieldtool.processing import pose, waterline
from fieldtool.processing.calibration import LensModel
from fieldtool.processing.frames import FrameSource
from fieldtool.processing.water_level import image_width
from fieldtool.processing.ortho import from_homography

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"
LINE_RAW_PX = [[300.0, 440.0], [1760.0, 580.0]]  # left bank grass -> right bank grass, across the water


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--png", default="")
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the real data")
    a = ap.parse_args()
    cfg = json.loads((a.data / "geul_dk_cam_config.json").read_text())
    lens = LensModel(np.array(cfg["camera_matrix"]), np.array(cfg["dist_coeffs"]).ravel(), (cfg["width"], cfg["height"]))
    src = FrameSource(a.data / "geul_dk_control.mp4")
    line = lens.undistort_points(np.array(LINE_RAW_PX))
    det = waterline.detect_water_edges((lens.undistort(f.image) for f in src), line)
    p = pose.solve_pose(np.array(cfg["gcps"]["src"], float), np.array(cfg["gcps"]["dst"], float), lens.camera_matrix,
                        lens.dist_coeffs)
    mapping = from_homography(pose.plane_homography(p, cfg["gcps"]["z_0"]), "pose", 0.0)
    w, sw, world = image_width(det["edges_px"], mapping, float(np.max(det["sigma_px"])))
    print(f"frames {det['n_frames']}, contrast {det['contrast']:.1f} (water activity {det['water_activity']:.1f}, "
          f"banks {np.round(det['bank_activity'], 2).tolist()} grey levels)")
    print(f"edges (undistorted px) {np.round(det['edges_px'], 1).tolist()}, 1-sigma {np.round(det['sigma_px'], 2).tolist()} px, "
          f"moved to the mean-image step: {det['refined_on_mean_image']}")
    print(f"width on the plane z_0 = {cfg['gcps']['z_0']} m: {w:.2f} ± {sw:.2f} m (1-sigma)")
    if a.png:
        from fieldtool.processing.frames import read_color_frame

        img = lens.undistort(read_color_frame(a.data / "geul_dk_control.mp4", 0.0, None))
        l0, l1 = det["line_px"].astype(int)
        cv2.line(img, tuple(l0), tuple(l1), (0, 255, 255), 2)
        for (x, y), s in zip(det["edges_px"], det["sigma_px"]):
            cv2.circle(img, (int(round(x)), int(round(y))), int(max(8, 3 * s)), (0, 0, 255), 3)
        prof = det["activity"] / max(det["activity"].max(), 1e-9)
        pts = l0[None] + np.linspace(0, 1, len(prof))[:, None] * (l1 - l0)[None] - np.c_[np.zeros(len(prof)), 120 * prof]
        cv2.polylines(img, [pts.astype(np.int32)], False, (255, 128, 0), 2)
        cv2.putText(img, f"edges found (red): width {w:.2f} +/- {sw:.2f} m on z0; activity profile (blue)", (40, 60),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    1.4, (0, 255, 255), 3)
        cv2.imwrite(a.png, cv2.resize(img, (960, 540)))
        print(f"wrote {a.png}")


if __name__ == "__main__":
    main()
