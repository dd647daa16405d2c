"""Discharge on analytic sections with analytic velocity fields."""

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


def test_missing_subsections_filled_by_depth_scaling():
    v = np.array([np.nan, 1.0, 1.0, np.nan])
    depth = np.array([0.5, 1.0, 1.0, 2.0])
    filled, flag = dq.fill_velocity(v, depth)
    assert filled[0] == pytest.approx(0.5 ** (2 / 3)) and filled[3] == pytest.approx(2 ** (2 / 3))
    assert list(flag) == [True, False, False, True]


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
