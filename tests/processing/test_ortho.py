"""Orthorectification from GCP distances / world points against a known homography."""

import numpy as np
import pytest

from fieldtool.errors import GeometryError, ParameterError
from fieldtool.processing import ortho

WORLD = np.array([[0.0, 10.0], [12.0, 11.0], [13.0, -1.0], [0.0, 0.0]])
H_WI = np.array([[40.0, -5.0, 300.0], [3.0, -30.0, 500.0], [0.001, -0.01, 1.0]])  # world -> image, seen from above


def _setup(world=WORLD):
    px = ortho._apply(H_WI, world)
    dist = [np.hypot(*(world[j] - world[i])) for i, j in ortho.PAIRS]
    return px, dist


def test_distances_recover_world_and_lengths():
    px, dist = _setup()
    m = ortho.from_distances(px, dist)
    np.testing.assert_allclose(m.gcp_world, WORLD, atol=1e-6)
    assert m.residual_m < 1e-6
    test = np.array([[350.0, 420.0], [500.0, 300.0]])
    a, b = m.image_to_world(test)
    ta, tb = ortho._apply(np.linalg.inv(H_WI), test)
    assert np.hypot(*(b - a)) == pytest.approx(np.hypot(*(tb - ta)), rel=1e-6)


def test_mirror_resolved_by_image_orientation():
    mirrored = WORLD * [-1, 1]
    px, dist = _setup(mirrored)
    m = ortho.from_distances(px, dist)
    # same distances as the unmirrored case, but the image quadrilateral's orientation decides
    assert np.sign(ortho._signed_area(m.gcp_world)) == np.sign(ortho._signed_area(mirrored))


def test_redundant_distance_residual_reported():
    px, dist = _setup()
    dist[1] += 0.30  # L2 taped 30 cm too long
    m = ortho.from_distances(px, dist)
    assert 0.02 < m.details["max_distance_residual_m"] < 0.3
    assert m.residual_m > 0.01


def test_triangle_inequality_violation_is_clear():
    px, dist = _setup()
    dist[4] = dist[2] + dist[3] + 5  # L5 > L3 + L4
    with pytest.raises(GeometryError, match=r"L3=\|P3P4\|, L4=\|P4P1\|, L5=\|P1P3\| cannot form a triangle"):
        ortho.from_distances(px, dist)
    with pytest.raises(ParameterError, match="six distances"):
        ortho.from_distances(px, dist[:5])


def test_world_points_and_velocity_rectification():
    px, _ = _setup()
    m = ortho.from_world_points(px, WORLD)
    # a displacement of 1 px along x at a node maps to the finite difference of the mapping
    x, y = np.array([400.0]), np.array([350.0])
    U, V = m.rectify_velocity(x, y, np.array([1.0]), np.array([0.0]))
    a = m.image_to_world(np.array([[399.999, 350.0], [400.001, 350.0]]))
    np.testing.assert_allclose([U[0], V[0]], (a[1] - a[0]) / 0.002, rtol=1e-5)


def test_points_outside_frame():
    px, dist = _setup()
    with pytest.raises(GeometryError, match=r"ortho.gcp_px\[0\]"):
        ortho.from_distances(px, dist, image_shape=(10, 10))


def test_rectified_image_axes():
    m = ortho.from_scale(0.01)  # 1 cm per pixel, nadir
    img = np.zeros((100, 200), np.uint8)
    img[10, 20] = 255
    out, A = m.rectified_image(img, bounds_m=(0.0, 2.0, -1.0, 0.0), resolution_m=0.01)
    X, Y = m.image_to_world(np.array([[20.0, 10.0]]))[0]
    col, row = (A @ [X, Y, 1])[:2]
    assert out[int(round(row)), int(round(col))] == 255


def test_two_points_similarity():
    """Two GCPs: scale, rotation and shift recovered exactly; the world frame puts P1 at 0 and P2 on +X."""
    from fieldtool.processing.ortho import from_two_points

    ang, scale = np.radians(30.0), 0.02  # m/px
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    px = np.array([[100.0, 200.0], [700.0, 500.0], [400.0, 100.0]])
    world = (scale * (R @ (px * [1, -1]).T)).T + [5.0, -3.0]
    m = from_two_points(px[:2], gcp_world=world[:2])
    np.testing.assert_allclose(m.image_to_world(px), world, atol=1e-9)
    d = float(np.linalg.norm(world[1] - world[0]))
    m2 = from_two_points(px[:2], d)
    w2 = m2.image_to_world(px)
    np.testing.assert_allclose(w2[0], [0, 0], atol=1e-9)
    np.testing.assert_allclose(w2[1], [d, 0], atol=1e-9)
    assert m2.details["m_per_px"] == pytest.approx(scale)
    # velocities: 10 px/s along the image x axis is 0.2 m/s whatever the rotation
    U, V = m2.rectify_velocity(np.array([300.0]), np.array([300.0]), np.array([10.0]), np.array([0.0]))
    assert np.hypot(U, V)[0] == pytest.approx(10 * scale)
    with pytest.raises(GeometryError, match="apart"):
        from_two_points([[10, 10], [12, 11]], 5.0)
    with pytest.raises(ParameterError, match="distances_m"):
        from_two_points(px[:2], None)


def test_scale_without_gcps_spans_the_outer_water_edges():
    """Thesis 8.2 with an island: the two picked points are the outer water edges, so the image scale is
    their distance on the cross-section (12 m), not the wetted width (11 m, island left out), which
    would make every velocity 8.3 % too low."""
    from types import SimpleNamespace

    from fieldtool.processing.cross_section import CrossSection
    from fieldtool.project.model import Project
    from fieldtool.run.geometry import build_mapping
    from fieldtool.run.inputs import Inputs

    cs = CrossSection(np.array([0, 2, 7.5, 8, 8.5, 9, 9.5, 14, 16.0]), np.array([11, 10, 8, 10, 10.4, 10, 8, 10, 11.0]))
    assert cs.wetted_width(10.0) == pytest.approx(11.0)
    left, right = cs.water_edges(10.0)
    assert right - left == pytest.approx(12.0)
    p = Project()
    p.ortho.method = "none"
    p.section.points_px = [[40.0, 300.0], [1240.0, 300.0]]  # 1200 px between the outer edges
    inputs = Inputs(cs, SimpleNamespace(shape=(720, 1280)), None, None)
    m = build_mapping(p, inputs, 10.0)
    assert m.details["m_per_px"] == pytest.approx(12.0 / 1200.0)
    assert 11.0 / 1200.0 / m.details["m_per_px"] - 1 == pytest.approx(-0.0833, abs=1e-3)  # the old scale's error


def test_the_quadrilateral_solver_finds_scipys_minimum():
    """ortho.levenberg_marquardt stands in for scipy.optimize.least_squares (import time); same minimum."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(3)
    for _ in range(20):
        quad = np.array([[0.0, 8.0], [12.0, 9.0], [11.0, -1.0], [0.0, 0.0]]) + rng.normal(0, 1.0, (4, 2))
        quad[3] = 0.0
        quad[0, 0] = 0.0
        L = np.array([np.hypot(*(quad[j] - quad[i])) for i, j in ortho.PAIRS]) + rng.normal(0, 0.05, 6)

        def resid(p, L=L):
            q = np.array([[0.0, p[0]], p[1:3], p[3:5], [0.0, 0.0]])
            return np.array([np.hypot(*(q[j] - q[i])) for i, j in ortho.PAIRS]) - L

        x0 = np.r_[quad[0, 1], quad[1], quad[2]] + rng.normal(0, 0.2, 5)
        ours = ortho.levenberg_marquardt(resid, x0)
        ref = least_squares(resid, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        assert np.sum(resid(ours) ** 2) <= np.sum(resid(ref) ** 2) + 1e-12
        np.testing.assert_allclose(ours, ref, atol=1e-6)
