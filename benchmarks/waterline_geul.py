"""Automatic water line on the real Geul clip (no truth): the edges found along a search line across the
river and 2 parallel lines each side (0.4 m apart on the authors' water plane z_0), their 1-sigma, the width
each line gives on that plane (pose from the 6 GCPs and their lens), and a picture for docs/.

    .venv/bin/python benchmarks/waterline_geul.py --png docs/waterline_geul.png

The Geul data hold no cross-section, so the width cannot be turned into a level here; the config's z_0
(138.27 m) is the authors' typed level, used only as the plane the widths are measured on. With a surveyed
section, `water_level.method = "waterline"` turns the same edges into a level (tests/processing/test_waterline.py).
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
from fieldtool.processing.ortho import from_homography
from fieldtool.processing.water_level import WATERLINE_WEAK_CONTRAST, image_width

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"
LINE_RAW_PX = [[300.0, 440.0], [1760.0, 580.0]]  # left bank grass -> right bank grass, across the water


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--png", default="")
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the real data")
    a = ap.parse_args()
    cfg = json.loads((a.data / "geul_dk_cam_config.json").read_text())
    lens = LensModel(np.array(cfg["camera_matrix"]), np.array(cfg["dist_coeffs"]).ravel(), (cfg["width"], cfg["height"]))
    p = pose.solve_pose(np.array(cfg["gcps"]["src"], float), np.array(cfg["gcps"]["dst"], float), lens.camera_matrix,
                        lens.dist_coeffs)
    mapping = from_homography(pose.plane_homography(p, cfg["gcps"]["z_0"]), "pose", 0.0)
    line = lens.undistort_points(np.array(LINE_RAW_PX))
    lines = waterline.parallel_lines(line, mapping, 0.4, 2, (cfg["height"], cfg["width"]))
    src = FrameSource(a.data / "geul_dk_control.mp4")
    det = waterline.detect_water_edges((lens.undistort(f.image) for f in src), lines)
    print(f"frames {det['n_frames']}")
    widths = []
    for ln in det["lines"]:
        if "error" in ln:
            print(f"line {ln['offset_m']:+.1f} m: no edges ({ln['error']})")
            continue
        w, sw, _ = image_width(ln["edges_px"], mapping, float(np.max(ln["sigma_px"])))
        widths.append(w)
        ln["width"] = (w, sw)
        print(f"line {ln['offset_m']:+.1f} m: contrast {ln['contrast']:.1f}, edges (undistorted px) "
              f"{np.round(ln['edges_px'], 1).tolist()}, still water walked {np.round(ln['still_water_px'], 0).tolist()} px, "
              f"width on z_0 = {cfg['gcps']['z_0']} m: {w:.2f} +- {sw:.2f} m")
    if len(widths) > 1:
        print(f"widths over {len(widths)} lines: median {np.median(widths):.2f} m, sd {np.std(widths, ddof=1):.2f} m")
    contrast = float(np.median([ln["contrast"] for ln in det["lines"] if "contrast" in ln]))
    weak = contrast < WATERLINE_WEAK_CONTRAST
    print(f"median activity contrast water / banks {contrast:.1f}" +
          (f": under {WATERLINE_WEAK_CONTRAST:g}, so with a cross-section the level would be graded doubtful" if weak else ""))
    if a.png:
        from fieldtool.processing.frames import read_color_frame

        img = lens.undistort(read_color_frame(a.data / "geul_dk_control.mp4", 0.0, None))
        for ln in det["lines"]:
            l0, l1 = ln["line_px"].astype(int)
            cv2.line(img, tuple(l0), tuple(l1), (0, 255, 255), 2 if ln["offset_m"] == 0 else 1)
            for (x, y) in ln.get("edges_px", []):
                cv2.circle(img, (int(round(x)), int(round(y))), 12, (0, 0, 255), 3)
        c = det["lines"][0]
        prof = c["activity"] / max(c["activity"].max(), 1e-9)
        l0, l1 = c["line_px"]
        pts = l0[None] + np.linspace(0, 1, len(prof))[:, None] * (l1 - l0)[None] - np.c_[np.zeros(len(prof)), 120 * prof]
        cv2.polylines(img, [pts.astype(np.int32)], False, (255, 128, 0), 2)
        txt = (f"water edges found (red) on 5 search lines (yellow), 0.4 m apart; width {np.median(widths):.2f} m "
               f"(sd {np.std(widths, ddof=1):.2f} m) on z0" if len(widths) > 1 else "edges found (red)")
        cv2.putText(img, txt, (30, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.15, (0, 255, 255), 3)
        cv2.putText(img, "activity along the centre line (blue). No cross-section: no level from these edges.",
                    (30, 110), cv2.FONT_HERSHEY_SIMPLEX, 1.15, (0, 255, 255), 3)
        cv2.putText(img, f"water/bank activity contrast {contrast:.1f}" + (" (weak: moving grass; some edges in the grass) "
                    "-> doubtful" if weak else ""), (30, 160), cv2.FONT_HERSHEY_SIMPLEX, 1.15, (0, 255, 255), 3)
        cv2.imwrite(a.png, cv2.resize(img, (960, 540), interpolation=cv2.INTER_AREA))
        print(f"wrote {a.png}")


if __name__ == "__main__":
    main()
