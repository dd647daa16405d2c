"""One project file, many editors (issue 25, item 1): three-way merge per key and per point, refusals of an
invalid or read-only file, and what each editor (TUI session, viewer) takes in from the other."""

import os
import stat

import pytest

from fieldtool.project.model import load_project, save_project
from fieldtool.project.sync import (
    MISSING,
    ProjectRefused,
    ProjectSync,
    merge3,
    set_path,
)
from fieldtool.project.template import write_template
from fieldtool.tui.session import Session
from fieldtool.viewer.picks import save_field

P = [[10.0, 20.0], [110.0, 20.0], [110.0, 120.0], [10.0, 120.0]]


def _project(tmp_path):
    path = write_template(tmp_path)
    s = Session(path)
    s.project.ortho.gcp_px = [list(p) for p in P]
    s.project.section.points_px = [[5.0, 60.0], [300.0, 62.0]]
    s.save()
    return path


# -- the merge --------------------------------------------------------------------------------------


def test_merge_takes_each_sides_own_points():
    base = {"ortho": {"gcp_px": P}}
    theirs = {"ortho": {"gcp_px": [P[0], [111.5, 21.5], P[2], P[3]]}}  # P2 re-picked elsewhere
    mine = {"ortho": {"gcp_px": [[9.0, 19.0], P[1], P[2], P[3]]}}  # P1 typed here
    merged, conflicts = merge3(base, theirs, mine)
    assert merged["ortho"]["gcp_px"] == [[9.0, 19.0], [111.5, 21.5], P[2], P[3]]
    assert conflicts == []


def test_merge_same_point_changed_both_ways_keeps_the_files_and_reports_it():
    base = {"section": {"points_px": [[1.0, 1.0], [2.0, 2.0]]}}
    theirs = {"section": {"points_px": [[1.0, 1.0], [3.0, 3.0]]}}
    mine = {"section": {"points_px": [[1.0, 1.0], [4.0, 4.0]]}}
    merged, conflicts = merge3(base, theirs, mine)
    assert merged == theirs
    assert [(c.key, c.mine, c.theirs) for c in conflicts] == [("section.points_px[1]", [4.0, 4.0], [3.0, 3.0])]


def test_merge_undo_elsewhere_and_a_new_point_here():
    base = {"o": {"g": P}}
    theirs = {"o": {"g": P[:3]}}  # undo of P4 in the viewer
    mine = {"o": {"g": [[0.0, 0.0]] + P[1:]}}  # P1 typed here
    merged, _ = merge3(base, theirs, mine)
    assert merged["o"]["g"] == [[0.0, 0.0]] + P[1:3]
    assert merge3({"a": 1}, {"a": 1}, {})[0] == {}  # a key removed here goes
    assert merge3({}, {"b": 2}, {"a": 1})[0] == {"b": 2, "a": 1}
    assert merge3(MISSING, MISSING, 5)[0] == 5


def test_set_path_sets_and_removes_points():
    d = {"ortho": {"gcp_px": [[1, 2], [3, 4]]}}
    assert set_path(d, "ortho.gcp_px[1]", [5, 6])["ortho"]["gcp_px"] == [[1, 2], [5, 6]]
    assert set_path(d, "ortho.gcp_px[1]", MISSING)["ortho"]["gcp_px"] == [[1, 2]]
    assert set_path(d, "water_level.value_m", 2.5)["water_level"] == {"value_m": 2.5}
    assert d == {"ortho": {"gcp_px": [[1, 2], [3, 4]]}}  # a copy


# -- the cases, two editors on one file ---------------------------------------------------


def test_p2_repicked_in_the_viewer_then_p1_typed_in_the_tui_keeps_p2(tmp_path):
    path = _project(tmp_path)
    tui = Session(path)
    viewer = ProjectSync(path)
    vp = viewer.load()
    vp.ortho.gcp_px[1] = [111.25, 22.5]
    assert viewer.save(vp).written
    tui.project.ortho.gcp_px[0] = [9.0, 19.0]  # typed before the TUI looked at the file again
    res = tui.save()
    assert res.conflicts == []
    assert load_project(path).ortho.gcp_px[:2] == [[9.0, 19.0], [111.25, 22.5]]
    assert tui.project.ortho.gcp_px[1] == [111.25, 22.5]  # the TUI shows the viewer's pick too


def test_p1_typed_in_the_tui_then_a_viewer_click_and_undo_keep_p1(tmp_path):
    path = _project(tmp_path)
    viewer = ProjectSync(path)
    vp = viewer.load()
    tui = Session(path)
    tui.project.ortho.gcp_px[0] = [9.0, 19.0]
    tui.save()
    vp.section.points_px[1] = [301.0, 61.0]  # the viewer's next click (on another mode), its P1 still old
    vp = viewer.save(vp).project  # the viewer shows what it saved: the merge
    assert load_project(path).ortho.gcp_px[0] == [9.0, 19.0] and vp.ortho.gcp_px[0] == [9.0, 19.0]
    tui.project.ortho.gcp_px[0] = [8.0, 18.0]
    tui.save()
    vp.ortho.gcp_px = vp.ortho.gcp_px[:3]  # Undo of P4 in the viewer, before it looked at the file again
    viewer.save(vp)
    got = load_project(path)
    assert got.ortho.gcp_px == [[8.0, 18.0]] + P[1:3] and got.section.points_px[1] == [301.0, 61.0]


def test_section_right_point_from_the_viewer_survives_a_tui_edit(tmp_path):
    path = _project(tmp_path)
    tui = Session(path)
    save_field(path, "section.points_px", [[5.0, 60.0], [290.0, 64.0]])
    tui.project.section.n_sub = 9
    tui.save()
    got = load_project(path)
    assert got.section.points_px[1] == [290.0, 64.0] and got.section.n_sub == 9


@pytest.mark.parametrize("bad", ["[ortho]\nnot_a_key = 3\n", "[ortho\ngcp_px = [\n"])
def test_a_file_saved_invalid_elsewhere_is_not_written_over(tmp_path, bad):
    path = _project(tmp_path)
    tui = Session(path)
    text = path.read_text() + "\n" + bad
    path.write_text(text)
    tui.project.section.n_sub = 7
    with pytest.raises(ProjectRefused, match="nothing was saved"):
        tui.save()
    assert path.read_text() == text
    assert tui.project.section.n_sub == 7  # the entry is kept in the window
    with pytest.raises(ProjectRefused):
        save_field(path, "ortho.gcp_px", P)
    assert path.read_text() == text


def test_a_read_only_file_is_refused_and_keeps_its_mode(tmp_path):
    path = _project(tmp_path)
    tui = Session(path)
    before = path.read_bytes()
    os.chmod(path, 0o444)
    try:
        tui.project.section.n_sub = 7
        with pytest.raises(ProjectRefused, match="read-only"):
            tui.save()
        with pytest.raises(ProjectRefused, match="read-only"):
            save_field(path, "section.n_sub", 3)
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o444 and path.read_bytes() == before
    finally:
        os.chmod(path, 0o644)


def test_a_save_keeps_the_files_mode(tmp_path):
    path = _project(tmp_path)
    os.chmod(path, 0o600)
    tui = Session(path)
    tui.project.section.n_sub = 8
    tui.save()
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600


def test_poll_sees_another_programs_change_and_writes_nothing(tmp_path):
    path = _project(tmp_path)
    tui = Session(path)
    assert tui.poll() is None
    save_field(path, "water_level.value_m", 12.5)
    before = path.read_bytes()
    res = tui.poll()
    assert res is not None and res.theirs_changed == ["water_level.value_m"]
    assert tui.project.water_level.value_m == 12.5 and path.read_bytes() == before
    assert tui.poll() is None


def test_a_value_typed_for_a_commented_out_key_takes_its_line(tmp_path):
    path = write_template(tmp_path)
    assert "# value_m =" in path.read_text()
    tui = Session(path)
    tui.project.water_level.value_m = 3.25
    tui.save()
    text = path.read_text()
    assert "# value_m =" not in text and text.count("value_m = 3.25") == 1
    block = text.split("[water_level]")[1].split("\n[")[0].splitlines()
    i = next(i for i, ln in enumerate(block) if ln.startswith("value_m = 3.25"))
    assert block[i + 1].startswith(("uncertainty_m", "# uncertainty_m"))  # in its place, not at the end
    assert "typed level" in block[i]  # the comment of the line is kept
    assert load_project(path).water_level.value_m == 3.25


def test_one_shot_writers_keep_other_keys(tmp_path):
    path = _project(tmp_path)
    ProjectSync(path).set_keys({"calibration.path": "cal.toml"})
    p = load_project(path)
    assert p.calibration.path == "cal.toml" and p.ortho.gcp_px == P
    save_project(p, path)  # the whole-file writer (init, synthetic scenes) still works
