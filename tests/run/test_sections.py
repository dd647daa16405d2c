"""Several sections of interest on one velocity field (thesis 10.3, RIVeR's summary table)."""

import json

import cv2
import numpy as np
import pytest

from fieldtool.errors import ParameterError
from fieldtool.project.model import load_project
from fieldtool.run.pipeline import run_project


def _section_px(truth, x_m: float) -> list[list[float]]:
    """Raw-frame pixels of the left and right water edges at X = x_m (the synthetic river is prismatic)."""
    r = truth.spec.river
    pts = np.array([[x_m, r.y_left_edge, r.level_m], [x_m, r.y_right_edge, r.level_m]])
    px, _ = cv2.projectPoints(pts, cv2.Rodrigues(truth.R)[0], truth.t, truth.K, truth.dist)
    return px.reshape(2, 2).tolist()


@pytest.mark.slow
def test_three_sections_each_near_the_truth(short_scene, tmp_path):
    p = load_project(short_scene.project_path)
    xs = short_scene.spec.river.x_section_m
    p.sections = [
        {"name": "upstream", "points_px": _section_px(short_scene, xs - 1.0)},
        {"name": "downstream", "points_px": _section_px(short_scene, xs + 1.0)[::-1]},
    ]  # picked right first
    res = run_project(p, tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    q_true = short_scene.discharge_m3s
    names = [e["name"] for e in doc["sections"]]
    assert names == ["main", "upstream", "downstream"]
    for e in doc["sections"]:
        assert abs(e["discharge_m3s"] / q_true - 1) < 0.03, e
        assert e["grade"] in ("good", "doubtful")
    assert doc["sections"][2].get("swapped") is True
    s = doc["sections_summary"]
    qs = np.array([e["discharge_m3s"] for e in doc["sections"]])
    assert s["n"] == 3 and s["mean_m3s"] == pytest.approx(qs.mean()) and s["std_m3s"] == pytest.approx(qs.std(ddof=1))
    assert s["cv"] == pytest.approx(s["std_m3s"] / s["mean_m3s"])
    assert res.discharge.discharge_m3s == doc["discharge_m3s"] == doc["sections"][0]["discharge_m3s"]


def test_bad_extra_section_is_named(short_scene):
    from fieldtool.project.validation import validate

    p = load_project(short_scene.project_path)
    p.sections = [{"name": "x", "points_px": [[1.0, 2.0]]}]
    assert any(pr.key == "sections[0].points_px" for pr in validate(p))
    p.sections = [{"name": "x", "points_px": [[1, 2], [3, 4]], "colour": "red"}]
    with pytest.raises(ParameterError, match=r"sections\[0\]\.colour"):
        run_project(p, None)


@pytest.mark.slow
def test_sections_crossing_an_island(tmp_path):
    """A 1.2 m bar in the river: the truth leaves it out, the surveyed cross-section shows it above the water,
    and both sections that cross it get the discharge right."""
    from fieldtool.synthetic import presets, render_scene

    truth = render_scene(presets.get("oblique", duration_s=1.5, river__island_m=(3.5, 4.7)), tmp_path / "s")
    assert truth.wetted_width_m == pytest.approx(12.0 - 1.2)
    p = load_project(truth.project_path)
    p.sections = [{"name": "upstream", "points_px": _section_px(truth, truth.spec.river.x_section_m - 1.0)}]
    res = run_project(p, None)
    assert res.discharge.wetted_width_m == pytest.approx(10.8, abs=0.05)
    for e in res.sections:
        assert abs(e["discharge_m3s"] / truth.discharge_m3s - 1) < 0.03, e


def test_report_lists_the_sections():
    from fieldtool.records.report import render_html

    summary = {
        "discharge_m3s": 10.0,
        "files": {},
        "sections": [
            {"name": "main", "discharge_m3s": 10.0, "discharge_ci95_m3s": [9.5, 10.5], "grade": "good"},
            {"name": "upstream", "discharge_m3s": 10.4, "discharge_ci95_m3s": None, "grade": "doubtful"},
            {"name": "far", "error": "section: crosses a bank"},
        ],
        "sections_summary": {"n": 2, "mean_m3s": 10.2, "std_m3s": 0.283, "cv": 0.0277},
    }
    html = render_html(summary, {}, [])
    assert "<h2>Sections</h2>" in html and "upstream" in html and "crosses a bank" in html
    assert "CV 2.8" in html and "9.5000 – 10.5000" in html


def test_tui_results_line_for_sections():
    from fieldtool.tui.screens.results import discharge_lines

    lines = discharge_lines(
        {
            "discharge_m3s": 10.0,
            "sections": [{"name": "main", "discharge_m3s": 10.0}, {"name": "up", "discharge_m3s": 10.4}],
            "sections_summary": {"n": 2, "mean_m3s": 10.2, "std_m3s": 0.283, "cv": 0.0277},
        }
    )
    assert any("sections" in ln and "CV 2.8 %" in ln and "up 10.400" in ln for ln in lines)


def test_viewer_section_list_pick_keeps_names():
    from fieldtool.viewer.picks import MODES

    st = MODES["sections"].make()
    st.load([{"name": "weir", "points_px": [[1.5, 2.5], [100.25, 3.0]], "cross_section": "weir.csv"}])
    st.click(10, 20)
    st.click(300, 40)
    v = st.value()
    assert v[0] == {"name": "weir", "points_px": [[1.5, 2.5], [100.25, 3.0]], "cross_section": "weir.csv"}
    assert v[1]["points_px"] == [[10.0, 20.0], [300.0, 40.0]] and v[1]["name"] == "section 3"
    assert [t for t, _ in st.labels()] == ["L2", "R2", "L3", "R3"]
    st.undo()
    assert len(st.value()) == 1 and st.pending == [10.0, 20.0]
