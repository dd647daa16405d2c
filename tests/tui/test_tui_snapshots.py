"""Snapshot of every TUI screen at 80 x 24 (pytest-textual-snapshot).

The project is small and fixed (a 160 x 120 px noise clip, a trapezoidal bed, four GCPs), so the
pictures depend only on the TUI. Update them after a deliberate change with
``pytest tests/tui/test_tui_snapshots.py --snapshot-update`` and look at the report.
"""

import json

import cv2
import numpy as np
import pytest

from fieldtool.project.model import (
    CrossSectionCfg,
    OrthoCfg,
    Project,
    RoiCfg,
    SectionCfg,
    VideoCfg,
    WaterLevelCfg,
    project_to_dict,
    save_project,
)
from fieldtool.tui.app import FieldToolApp
from fieldtool.tui.steps import STEP_IDS

SIZE = (80, 24)


def make_project(root, step: str, **changes) -> FieldToolApp:
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(7)
    w = cv2.VideoWriter(str(root / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120))
    base = cv2.GaussianBlur(rng.uniform(0, 255, (120, 200)).astype(np.float32), (0, 0), 1.5)
    for i in range(10):
        frame = np.clip(base[:, 2 * i : 2 * i + 160] * 1.5 - 60, 0, 255).astype(np.uint8)
        w.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    w.release()
    (root / "bed.csv").write_text("station,elevation\n0,2\n1,0.5\n4,0.4\n5,2\n")
    p = Project(name="snapshot river", step=step, root=root)
    p.video = VideoCfg(path="clip.avi", end_s=0.8)
    p.cross_section = CrossSectionCfg(path="bed.csv")
    p.ortho = OrthoCfg(gcp_px=[[20, 100], [140, 100], [130, 20], [30, 20]], distances_m=[4, 3, 4, 3, 5, 5])
    p.water_level = WaterLevelCfg(value_m=1.5)
    p.roi = RoiCfg(rect_px=[10, 10, 150, 110])
    p.section = SectionCfg(points_px=[[30, 60], [130, 60]], n_sub=5)
    p.filters = [{"name": "clahe", "clip_limit": 2.0}]
    for key, value in changes.items():
        table, name = key.split("__")
        setattr(getattr(p, table), name, value)
    save_project(p, root / "project.toml")
    return p


def fake_result(root, p: Project, n: int = 5, quality: bool = False) -> None:
    """result.json and subsections.csv as a run writes them (numbers made up, inputs current);
    ``quality``: with the 95 % interval and the quality verdict."""
    out = root / "out"
    out.mkdir()
    summary = {
        "discharge_m3s": 1.2345,
        "discharge_p05_m3s": 1.1,
        "discharge_p95_m3s": 1.35,
        "water_level_m": 1.5,
        "water_level_method": "value",
        "water_level_uncertainty_m": 0.01,
        "wetted_area_m2": 4.2,
        "wetted_width_m": 4.4,
        "mean_velocity_ms": 0.294,
        "alpha": 0.8,
        "alpha_default": True,
        "n_pairs": 7,
        "valid_fraction_mean": 0.9,
        "warnings": [],
        "files": {"result": "result.json", "subsections": "subsections.csv", "section_png": "section.png"},
        "inputs": project_to_dict(p),
    }
    if quality:
        summary["discharge_ci95_m3s"] = [1.069, 1.4]
        summary["quality"] = {
            "grade": "doubtful",
            "reasons": [
                {
                    "code": "valid_fraction",
                    "severity": "doubtful",
                    "message": "few valid vectors (38 % < 50 %)",
                    "value": 0.38,
                    "threshold": 0.5,
                }
            ],
        }
    (out / "result.json").write_text(json.dumps(summary))
    rows = [
        "subsection,station_from_m,station_to_m,area_m2,mean_depth_m,surface_velocity_ms,velocity_filled,discharge_m3s"
    ]
    w = 4.4 / n
    for i in range(n):
        rows.append(f"{i + 1},{0.3 + w * i:.4f},{0.3 + w * (i + 1):.4f},0.84,0.95,0.37,{int(i == n - 1)},0.25")
    (out / "subsections.csv").write_text("\n".join(rows) + "\n")


@pytest.mark.parametrize("step", [s for s in STEP_IDS if s != "results"])
def test_screen(step, tmp_path, snap_compare):
    make_project(tmp_path / "m", step)
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), terminal_size=SIZE)


def test_filter_preview(tmp_path, snap_compare):
    """ctrl+r on the filters step: before / after at the size of the terminal."""
    make_project(tmp_path / "m", "filters")
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), press=["ctrl+r", "_"], terminal_size=SIZE)


def test_results_screen(tmp_path, snap_compare):
    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p)
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), terminal_size=SIZE)


def test_results_with_interval_grade_and_15_subsections(tmp_path, snap_compare):
    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p, n=15, quality=True)
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), terminal_size=SIZE)


def test_ortho_with_empty_gcps(tmp_path, snap_compare):
    """Missing entries take no line: red label and "✗ required" in the input; L1-L6 stay on screen."""
    make_project(tmp_path / "m", "ortho", ortho__gcp_px=[])
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), terminal_size=SIZE)


def test_sidebar_with_a_wrong_step(tmp_path, snap_compare):
    """Start 10 s past the end of a 1 s clip: ✗ and the reason under the video step."""
    make_project(tmp_path / "m", "cross_section", video__start_s=10.0, video__end_s=None)
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), terminal_size=SIZE)


def test_cross_section_from_a_shape(tmp_path, snap_compare):
    make_project(
        tmp_path / "m",
        "cross_section",
        cross_section__shape="trapezoidal",
        cross_section__top_width_m=6.0,
        cross_section__bottom_width_m=2.0,
        cross_section__depth_m=1.2,
        cross_section__bank_elevation_m=2.0,
    )
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), terminal_size=SIZE)


def test_invalid_entry_blocks_next(tmp_path, snap_compare):
    make_project(tmp_path / "m", "piv")
    press = ["end", "ctrl+u", "4", "ctrl+n"]  # window 4 px: refused, message shown, still on PIV
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), press=press, terminal_size=SIZE)


def test_calibration_run_mode(tmp_path, snap_compare):
    make_project(tmp_path / "m", "calibration")
    press = ["enter", "down", "down", "enter", "_"]  # choose "calibrate from a checkerboard video"
    assert snap_compare(FieldToolApp(tmp_path / "m" / "project.toml"), press=press, terminal_size=SIZE)
