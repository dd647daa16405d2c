"""Cross-section geometry against hand-computed areas, widths and perimeters."""

import numpy as np
import pytest

from fieldtool.errors import GeometryError, InputFileError, ParameterError
from fieldtool.processing.cross_section import CrossSection, from_shape, parse_xy_text, to_csv_text


def test_rectangular():
    cs = from_shape("rectangular", top_width_m=8, depth_m=2, bank_elevation_m=10)
    assert cs.wetted_area(9.5) == pytest.approx(8 * 1.5, rel=1e-5)
    assert cs.wetted_width(9.5) == pytest.approx(8, rel=1e-5)
    assert cs.wetted_perimeter(9.5) == pytest.approx(8 + 2 * 1.5, rel=1e-5)


def test_trapezoidal_area_width_perimeter():
    cs = from_shape("trapezoidal", top_width_m=10, bottom_width_m=4, depth_m=2, bank_elevation_m=100)
    # at 1 m depth: top width 4 + 2*1.5 = 7, area (4+7)/2*1
    assert cs.wetted_width(99) == pytest.approx(7)
    assert cs.wetted_area(99) == pytest.approx(5.5)
    assert cs.wetted_perimeter(99) == pytest.approx(4 + 2 * np.hypot(1.5, 1))
    assert cs.water_edges(99) == pytest.approx((1.5, 8.5))


def test_parabolic_area():
    cs = from_shape("parabolic", top_width_m=10, depth_m=2, n_parabola=2001)
    assert cs.wetted_area(0.0 - 1e-9) == pytest.approx(2 / 3 * 10 * 2, rel=1e-4)


def test_partial_area_sums_to_total():
    cs = from_shape("parabolic", top_width_m=12, depth_m=1.5, left_station_m=3)
    edges = np.linspace(3, 15, 7)
    parts = sum(cs.wetted_area(-0.3, a, b) for a, b in zip(edges[:-1], edges[1:], strict=True))
    assert parts == pytest.approx(cs.wetted_area(-0.3))


def test_parse_separators_and_header():
    for text in (
        "x,y\n0,5\n1,3\n2,5\n",
        "0;5\n1;3\n2;5",
        "0 5\n1\t3\n2 5\n",
        "# survey\nstation elevation\n0 5\n1 3\n2 5",
    ):
        cs = parse_xy_text(text)
        assert list(cs.station) == [0, 1, 2] and list(cs.elevation) == [5, 3, 5]
    cs = from_shape("trapezoidal", top_width_m=10, bottom_width_m=4, depth_m=2)
    back = parse_xy_text(to_csv_text(cs))
    np.testing.assert_allclose(back.station, cs.station, atol=1e-4)


def test_a_point_read_twice_and_vertical_walls_are_taken():
    """A concrete channel surveyed down its left wall and up its right one (two rows at each wall's station), and a
    point read twice: the repeat is dropped, a wall's rows are set WALL_STEP_M apart; the wetted area is the
    rectangle's to within that step times the walls' height. A station that goes back is still refused."""
    from fieldtool.processing.cross_section import WALL_STEP_M

    cs = parse_xy_text("0,10\n0,8\n2.5,8\n2.5,8\n5,8\n5,10\n", "channel.csv")
    assert len(cs.station) == 5 and np.all(np.diff(cs.station) > 0)
    assert cs.station[1] == pytest.approx(WALL_STEP_M) and cs.station[-1] == pytest.approx(5 + WALL_STEP_M)
    assert cs.wetted_area(9.0) == pytest.approx(5.0, abs=2 * WALL_STEP_M)
    with pytest.raises(InputFileError, match="station must increase"):
        parse_xy_text("0,10\n0,8\n-0.5,8\n5,10\n", "channel.csv")
    with pytest.raises(InputFileError, match="line 2: .* over a 0 m wide section"):  # every row at one station
        parse_xy_text("0,10\n0,8\n0,10\n", "channel.csv")
    free = from_shape("free", points=[[0, 10], [0, 8], [5, 8], [5, 10]])  # the project's own points, the same
    assert free.wetted_area(9.0) == pytest.approx(5.0, abs=2 * WALL_STEP_M)


def test_bad_sections():
    with pytest.raises(InputFileError, match="at least 2 rows"):
        parse_xy_text("0,1\n", "bed.csv")
    with pytest.raises(InputFileError, match="bed.csv: cross-section: station must increase.*row 3"):
        parse_xy_text("0,1\n1,0\n0.5,1\n", "bed.csv")
    with pytest.raises(InputFileError, match="line 3"):
        parse_xy_text("0,1\n1,0\nabc,1\n", "bed.csv")
    with pytest.raises(ParameterError, match="bottom_width_m"):
        from_shape("trapezoidal", top_width_m=4, bottom_width_m=6, depth_m=1)
    with pytest.raises(ParameterError, match="not one of"):
        from_shape("round", top_width_m=4, depth_m=1)


def test_level_checks():
    cs = CrossSection(np.array([0, 2, 4, 6.0]), np.array([5, 2, 2.5, 4.0]))
    with pytest.raises(GeometryError, match="below the lowest bed point"):
        cs.check_level(1.0)
    with pytest.raises(GeometryError, match="above both banks"):
        cs.check_level(6.0)
    with pytest.raises(GeometryError, match="above the right bank"):
        cs.check_level(4.5)
    cs.check_level(3.0)
