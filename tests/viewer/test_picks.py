"""Pick-mode state machines (fieldtool.viewer.picks): order, undo, polygon closing, values."""

import pytest

from fieldtool.project.model import Project, load_project, save_project
from fieldtool.viewer.mapping import PlotAxes
from fieldtool.viewer.picks import (
    MODES,
    PointsPick,
    PolygonListPick,
    RectListPick,
    RectPick,
    StationPick,
    get_field,
    set_field,
)


def test_gcps_are_numbered_in_click_order_and_stop_at_four():
    st = MODES["gcp"].make()
    clicks = [(10, 20), (300, 25), (310, 200), (5, 190)]
    for k, (x, y) in enumerate(clicks):
        assert not st.complete
        msg = st.click(x, y)
        assert f"P{k + 1}" in msg
    assert st.complete
    assert st.value() == [[10, 20], [300, 25], [310, 200], [5, 190]]
    assert [t for t, _ in st.labels()] == ["P1", "P2", "P3", "P4"]
    st.click(1, 1)  # a fifth click is refused
    assert len(st.value()) == 4 and "all 4" in st.click(2, 2)


def test_points_undo_removes_the_last_and_lets_it_be_placed_again():
    st = PointsPick(("L", "R"))
    st.click(1, 2)
    st.click(3, 4)
    assert "R" in st.undo()
    assert st.value() == [[1, 2]]
    st.click(7, 8)
    assert st.value() == [[1, 2], [7, 8]]
    st.undo(), st.undo()
    assert st.value() == [] and st.undo() == "nothing to undo"


def test_points_load_keeps_the_existing_picks_for_undo():
    st = PointsPick(("P1", "P2", "P3", "P4"))
    st.load([[1, 1], [2, 2], [3, 3], [4, 4]])
    assert st.complete
    st.undo()
    st.click(9, 9)
    assert st.value()[-1] == [9, 9]


def test_rectangle_is_normalised_and_saved_only_when_complete():
    st = RectPick()
    st.click(400, 300)
    assert st.value() is ...  # one corner: nothing to save yet
    st.click(100, 50)
    assert st.value() == [100, 50, 400, 300]
    st.undo()
    assert st.value() is ...
    st.undo()
    assert st.value() == []  # all undone: the field is cleared
    st.click(1, 2), st.click(3, 4), st.click(50, 60)  # a third click starts a new rectangle
    assert st.value() is ... and st.labels() == [("C1", [50, 60])]


def test_stable_regions_undo_reopens_the_last_rectangle():
    st = RectListPick()
    for xy in [(0, 0), (10, 10), (50, 40), (20, 60)]:
        st.click(*xy)
    assert st.value() == [[0, 0, 10, 10], [20, 40, 50, 60]]
    st.undo()  # second region loses its second corner
    assert st.value() == [[0, 0, 10, 10]] and st.pending == [50, 40]
    st.click(70, 80)
    assert st.value() == [[0, 0, 10, 10], [50, 40, 70, 80]]
    st.undo(), st.undo(), st.undo()
    assert st.value() == [] and st.pending == [0, 0]


def test_polygon_needs_three_vertices_and_closes_on_the_first_vertex():
    st = PolygonListPick(close_tol_px=5)
    st.click(0, 0)
    st.click(100, 0)
    assert "at least 3" in st.close()
    assert st.value() == []
    st.click(100, 100)
    st.click(2, 3)  # within 5 px of the first vertex: closes instead of adding a vertex
    assert st.value() == [[[0, 0], [100, 0], [100, 100]]] and st.open == []


def test_polygon_close_button_undo_vertex_and_reopen():
    st = PolygonListPick()
    for xy in [(0, 0), (10, 0), (10, 10), (0, 10)]:
        st.click(*xy)
    st.undo()  # last vertex of the open polygon
    assert st.open == [[0, 0], [10, 0], [10, 10]]
    assert "closed" in st.close()
    for xy in [(50, 50), (60, 50), (60, 60)]:
        st.click(*xy)
    assert len(st.value()) == 1  # the open polygon is not saved
    st.close()
    assert len(st.value()) == 2
    st.undo()  # reopens mask 2
    assert len(st.value()) == 1 and len(st.open) == 3
    st.undo()
    assert st.open == [[50, 50], [60, 50]]
    assert [t for t, _ in st.labels()] == ["M1", "2.1", "2.2"]


def test_station_pick_maps_the_click_through_the_axes():
    ax = PlotAxes(100, 900, 50, 550, x_min=0.0, x_max=20.0, y_min=95.0, y_max=100.0)
    st = StationPick(ax)
    assert st.value() is None
    assert "inside" in st.click(50, 300)  # left of the plotting area
    col = 100 + 7.25 / 20.0 * 800
    st.click(col, 300)
    assert st.value() == pytest.approx(7.25, abs=1e-3)
    st.click(col + 40, 300)  # a new click replaces the point
    assert st.value() == pytest.approx(8.25, abs=1e-3)
    st.undo()
    assert st.value() is None
    st.load(12.5)
    assert st.value() == pytest.approx(12.5, abs=1e-3)


def test_every_mode_fills_an_existing_project_field(tmp_path):
    """The field paths are real, and the values survive a save/load of the project file."""
    p = Project()
    values = {}
    ax = PlotAxes(0, 100, 0, 100, 0.0, 10.0, 0.0, 1.0)
    for spec in MODES.values():
        st = spec.make(axes=ax)
        get_field(p, spec.field)  # exists
        for x, y in [(10, 20), (30, 40), (50, 25), (10.5, 20.5)]:
            st.click(x, y)
        st.close()
        values[spec.field] = st.value()
        set_field(p, spec.field, st.value())
    save_project(p, tmp_path / "p.toml")
    back = load_project(tmp_path / "p.toml")
    for field, v in values.items():
        assert get_field(back, field) == v
    with pytest.raises(AttributeError):
        set_field(p, "ortho.no_such_key", 1)
