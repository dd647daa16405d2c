"""Discharge on analytic sections with analytic velocity fields."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from fieldtool.errors import GeometryError
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho
from fieldtool.processing.cross_section import from_shape


def _uniform_field(mapping, speed_ms, direction, shape=(40, 60), spacing=10.0):
    ny, nx = shape
    y, x = np.mgrid[0:ny, 0:nx] * spacing + 5.0
    J = mapping.jacobian(x, y)
    Jinv = np.linalg.inv(J)
    Vw = np.array(direction) * speed_ms
    u = Jinv[..., 0, 0] * Vw[0] + Jinv[..., 0, 1] * Vw[1]
    v = Jinv[..., 1, 0] * Vw[0] + Jinv[..., 1, 1] * Vw[1]
    return x, y, u, v


def test_rectangular_uniform_flow_exact():
    # nadir, 2 cm/px; world = (0.02 x, -0.02 y); river 8 m wide along X, flowing +X
    m = ortho.from_scale(0.02)
    cs = from_shape("rectangular", top_width_m=8, depth_m=2, bank_elevation_m=10)
    level = 9.5
    # section across the flow: left edge (looking downstream +X) is at larger Y = smaller image y
    p1, p2 = np.array([300.0, 50.0]), np.array([300.0, 450.0])  # 400 px = 8 m
    geom = dq.section_geometry([p1, p2], m, cs, level, n_sub=10)
    np.testing.assert_allclose(geom.normal, [1.0, 0.0], atol=1e-12)
    x, y, u, v = _uniform_field(m, 0.7, (1.0, 0.0), shape=(60, 80))
    U, V = m.rectify_velocity(x, y, u, v)
    vs = dq.subsection_velocity(geom, x, y, U, V)
    np.testing.assert_allclose(vs, 0.7, rtol=1e-9)
    res = dq.compute_discharge(geom, cs, level, vs, alpha=0.85)
    assert res.discharge_m3s == pytest.approx(0.85 * 0.7 * 8 * 1.5, rel=1e-5)
    assert res.mean_velocity_ms == pytest.approx(0.85 * 0.7, rel=1e-5)


def test_default_alpha_rule():
    assert dq.default_alpha(1.2) == 0.8 and dq.default_alpha(2.5) == 0.9


def test_missing_subsections_filled_along_the_manning_law():
    v = np.array([np.nan, 1.0, 1.0, np.nan])
    depth = np.array([0.5, 1.0, 1.0, 2.0])  # flat-bed subsections: both means of depth^(2/3) are depth^(2/3)
    filled, flag = dq.fill_velocity(v, (depth ** (2 / 3), depth ** (2 / 3)))
    assert filled[0] == pytest.approx(0.5 ** (2 / 3)) and filled[3] == pytest.approx(2 ** (2 / 3))
    assert list(flag) == [True, False, False, True]


def test_manning_factors_weigh_by_depth_as_the_discharge_does():
    # V channel, depth s/2 near the left edge: over [0, a] the depth-weighted mean of d^(2/3) is
    # (3/2)(1/2)^(5/3) a^(2/3); the plain mean over [a, 2a] is (1/2)^(2/3)(3/5)((2a)^(5/3) - a^(5/3))/a
    cs = from_shape("free", points=[[0, 10], [4, 8], [8, 10]])
    to, frm = dq.manning_factors(cs, 10.0, np.array([0.0, 0.8, 1.6]), k=400)
    a = 0.8
    assert to[0] == pytest.approx(1.5 * 0.5 ** (5 / 3) * a ** (2 / 3), rel=1e-3)
    assert frm[1] == pytest.approx(0.5 ** (2 / 3) * 0.6 * ((2 * a) ** (5 / 3) - a ** (5 / 3)) / a, rel=1e-3)


def test_no_valid_vector_is_an_error():
    m = ortho.from_scale(0.02)
    cs = from_shape("rectangular", top_width_m=8, depth_m=2)
    geom = dq.section_geometry([[0, 0], [0, 400]], m, cs, -0.5, 4)
    with pytest.raises(GeometryError, match="no valid velocity"):
        dq.compute_discharge(geom, cs, -0.5, np.full(4, np.nan))


def test_sample_field_ignores_invalid_nodes():
    y, x = np.mgrid[0:3, 0:3] * 10.0
    U = np.ones((3, 3))
    U[1, 1] = np.nan
    V = np.zeros((3, 3))
    su, _ = dq.sample_field(x, y, U, V, np.array([[12.0, 10.0], [5.0, 5.0], [100.0, 0.0]]))
    assert su[0] == 1.0 and su[1] == 1.0 and np.isnan(su[2])


def test_section_outside_frame():
    m = ortho.from_scale(0.02)
    cs = from_shape("rectangular", top_width_m=8, depth_m=2)
    with pytest.raises(GeometryError, match=r"section.points_px\[1\]"):
        dq.section_geometry([[0, 0], [0, 900]], m, cs, -0.5, 4, image_shape=(720, 1280))


def _triangle_setup():
    # nadir, 2 cm/px, a V channel 8 m wide and 2 m deep at the level (bank top = level), section across +X flow
    m = ortho.from_scale(0.02)
    cs = from_shape("free", points=[[0, 10], [4, 8], [8, 10]])
    return m, cs, 10.0, ([300.0, 50.0], [300.0, 450.0])


def test_samples_whose_windows_reach_a_bank_are_left_out():
    m, cs, level, pts = _triangle_setup()
    assert dq.section_geometry(pts, m, cs, level, 10).trusted is None  # no footprint: every sample
    geom = dq.section_geometry(pts, m, cs, level, 10, footprint_px=32)  # 32 px = 0.64 m from each sample
    stations = (np.arange(10)[:, None] + (np.arange(dq.SAMPLES_PER_SUB)[None, :] + 0.5) / dq.SAMPLES_PER_SUB) * 0.8
    np.testing.assert_array_equal(geom.trusted, (stations > 0.64) & (stations < 8 - 0.64))
    assert geom.trusted[0].any() and not geom.trusted[0].all() and geom.trusted[1:-1].all()


def test_an_edge_subsection_out_of_reach_takes_the_depth_scaled_neighbour():
    # a field that reads the interior speed right up to the banks, as a window half on a blanked bank does
    m, cs, level, pts = _triangle_setup()
    x, y, u, v = _uniform_field(m, 0.7, (1.0, 0.0), shape=(60, 80))
    U, V = m.rectify_velocity(x, y, u, v)
    plain = dq.section_geometry(pts, m, cs, level, 10)
    geom = dq.section_geometry(pts, m, cs, level, 10, footprint_px=50)  # 1 m: no sample of the edge subsections
    vs = dq.subsection_velocity(geom, x, y, U, V)
    assert np.isnan(vs[[0, -1]]).all() and np.allclose(vs[1:-1], 0.7)
    res = dq.compute_discharge(geom, cs, level, vs, alpha=0.85)
    ref = dq.compute_discharge(plain, cs, level, dq.subsection_velocity(plain, x, y, U, V), alpha=0.85)
    to, frm = dq.manning_factors(cs, level, geom.station_edges)
    assert res.surface_velocity_ms[0] == pytest.approx(0.7 * to[0] / frm[1])
    assert list(np.flatnonzero(res.velocity_filled)) == [0, 9]
    assert res.discharge_m3s < ref.discharge_m3s
    assert any("water edge" in w for w in res.warnings) and not any("no valid vector" in w for w in res.warnings)


def test_a_narrow_stream_under_large_windows_keeps_every_sample_and_says_so():
    m, cs, level, pts = _triangle_setup()
    geom = dq.section_geometry(pts, m, cs, level, 10, footprint_px=150)  # 3 m reach on an 8 m stream
    assert geom.trusted.all() and "all samples kept" in geom.edge_note


def test_profile_band_gives_no_percentile_where_no_pair_measured_and_no_warning(monkeypatch):
    """A subsection that no pair measured (or fewer than 3) has NaN for its band, computed without NumPy's
    All-NaN warning; the others have their pairs' percentiles."""
    rows = iter([np.array([1.0, np.nan, 0.5]), np.array([1.2, np.nan, np.nan]), np.array([0.9, np.nan, 0.6])])
    monkeypatch.setattr(dq, "subsection_velocity", lambda *a: next(rows))
    mapping = SimpleNamespace(rectify_velocity=lambda x, y, u, v: (u, v))
    piv = SimpleNamespace(x=None, y=None, u_pairs=[0, 1, 2], v_pairs=[0, 1, 2])
    d = SimpleNamespace(
        area_m2=np.ones(3),
        station_from=np.array([0.0, 1.0, 2.0]),
        station_to=np.array([1.0, 2.0, 3.0]),
        surface_velocity_ms=np.array([1.0, 1.0, 0.5]),
        velocity_filled=np.array([False, True, False]),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = dq.profile_band(d, piv, None, mapping)
    assert b["p025_ms"][0] == pytest.approx(np.percentile([1.0, 1.2, 0.9], 2.5))
    assert b["p975_ms"][0] == pytest.approx(np.percentile([1.0, 1.2, 0.9], 97.5))
    assert np.isnan(b["p025_ms"][1:]).all() and np.isnan(b["p975_ms"][1:]).all()
    assert list(b["n_pairs"]) == [3, 0, 2]
