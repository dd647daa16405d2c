"""Synthetic scene generator: the truth it claims and the video it writes agree with independent checks."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.special import beta

from fieldtool.errors import Cancelled
from fieldtool.processing.cross_section import load_cross_section
from fieldtool.project.model import load_project
from fieldtool.synthetic import River, gcp_distances, gcp_world, presets, render_scene
from fieldtool.synthetic.checkerboard import render_checkerboard


def test_true_discharge_rectangular_uniform():
    # a = b = 0: rectangular channel, uniform surface velocity -> Q = alpha * U * W * D exactly
    r = River(width_m=10.0, depth_m=2.0, shape_a=0.0, shape_b=0.0, u_max_ms=1.3, alpha=0.85)
    t = r.truth()
    assert t["discharge_m3s"] == pytest.approx(0.85 * 1.3 * 10.0 * 2.0, rel=1e-9)
    assert t["wetted_area_m2"] == pytest.approx(20.0, rel=1e-9)
    assert t["mean_velocity_ms"] == pytest.approx(0.85 * 1.3, rel=1e-9)


def test_true_discharge_parabola_closed_form():
    # a = b = 1: d = 4 D u (1 - u); area = 2/3 W D; Q = alpha U W D 4^(5/3) B(8/3, 8/3)
    W, D, U, a = 12.0, 1.5, 1.1, 0.9
    t = River(width_m=W, depth_m=D, shape_a=1.0, shape_b=1.0, u_max_ms=U, alpha=a).truth()
    assert t["wetted_area_m2"] == pytest.approx(2.0 / 3.0 * W * D, rel=1e-8)
    assert t["discharge_m3s"] == pytest.approx(a * U * W * D * 4 ** (5 / 3) * beta(8 / 3, 8 / 3), rel=1e-7)


def test_survey_matches_analytic_section():
    r = presets.get("oblique").river
    cs = r.survey(0.25)
    assert cs.wetted_width(r.level_m) == pytest.approx(r.width_m, rel=1e-9)
    # a piecewise-linear survey every 0.25 m holds the analytic area to well under 1 %
    assert cs.wetted_area(r.level_m) == pytest.approx(r.truth()["wetted_area_m2"], rel=5e-3)
    assert cs.water_edges(r.level_m) == pytest.approx((r.s_left, r.s_right), abs=1e-9)


@pytest.mark.parametrize(
    "name,kw", [("oblique", {}), ("oblique", {"distortion": True}), ("far_bank", {}), ("nadir", {})]
)
def test_gcp_projection_round_trip(name, kw):
    spec = presets.get(name, **kw)
    cam = spec.camera
    gw = gcp_world(spec)
    px = cam.project(gw)
    assert np.all((px > 0) & (px < [cam.width_px - 1, cam.height_px - 1])), "GCPs must be in view"
    ideal = cam.undistorted_of_distorted(px)
    back = cv2.perspectiveTransform(ideal.reshape(-1, 1, 2), np.linalg.inv(cam.plane_homography(spec.river.level_m)))
    np.testing.assert_allclose(back.reshape(-1, 2), gw[:, :2], atol=1e-6)
    # the homography and cv2.projectPoints agree on the undistorted image
    via_h = cv2.perspectiveTransform(gw[:, :2].reshape(-1, 1, 2), cam.plane_homography(spec.river.level_m)).reshape(
        -1, 2
    )
    np.testing.assert_allclose(via_h, cam.project(gw, distort=False), atol=1e-6)
    # taped distances: opposite sides of the rectangle of targets are equal, diagonals too
    L = gcp_distances(gw)
    assert L[0] == pytest.approx(L[2]) and L[1] == pytest.approx(L[3]) and L[4] == pytest.approx(L[5])
    assert L[4] == pytest.approx(np.hypot(L[0], L[1]))


@pytest.fixture(scope="module")
def nadir_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("nadir")
    calls = []
    spec = presets.get("nadir", duration_s=0.2)
    truth = render_scene(spec, out, progress=lambda d, n: calls.append((d, n)))
    return spec, truth, out, calls


def test_nadir_particles_move_by_expected_pixels(nadir_scene):
    spec, truth, _, calls = nadir_scene
    assert calls[-1] == (spec.n_frames, spec.n_frames) and len(calls) == spec.n_frames
    r, cam = spec.river, spec.camera
    s_star = r.s_left + r.shape_a / (r.shape_a + r.shape_b) * r.width_m  # deepest point: du/ds = 0
    y_star = float(r.y_of_station(s_star))
    lag = 4
    # expected image shift: the projected displacement of the surface, Hann-weighted over the patch rows
    c = cam.project(np.array([[r.x_section_m, y_star, r.level_m]]))[0]
    cx, cy = int(round(c[0])), int(round(c[1]))
    half = 48
    rows = np.arange(cy - half, cy + half)
    world_y = cv2.perspectiveTransform(
        np.column_stack([np.full(len(rows), float(cx)), rows.astype(float)]).reshape(-1, 1, 2),
        np.linalg.inv(cam.plane_homography(r.level_m)),
    ).reshape(-1, 2)[:, 1]
    u = r.surface_velocity_y(world_y)
    shift_m = lag / spec.fps * np.sum(np.hanning(2 * half) * u) / np.hanning(2 * half).sum()
    expected = shift_m * cam.K[0, 0] / (cam.position_m[2] - r.level_m)  # nadir: px per m = f / height
    cap = cv2.VideoCapture(str(truth.video_path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(
            cv2.cvtColor(f, cv2.COLOR_BGR2GRAY).astype(np.float64)[cy - half : cy + half, cx - half : cx + half]
        )
    assert len(frames) == spec.n_frames
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(spec.fps)
    win = cv2.createHanningWindow((2 * half, 2 * half), cv2.CV_64F)
    shifts = np.array([cv2.phaseCorrelate(frames[i], frames[i + lag], win)[0] for i in range(len(frames) - lag)])
    assert expected > 6.0
    np.testing.assert_allclose(shifts[:, 0], expected, rtol=0.03)  # flow along +X = image +x
    np.testing.assert_allclose(shifts[:, 1], 0.0, atol=0.15)


def test_written_project_loads_and_matches_truth(nadir_scene):
    spec, truth, out, _ = nadir_scene
    proj = load_project(truth.project_path)
    assert proj.resolve(proj.video.path).is_file()
    cs = load_cross_section(proj.resolve(proj.cross_section.path))
    assert cs.wetted_width(proj.water_level.value_m) == pytest.approx(truth.wetted_width_m, rel=1e-6)
    assert proj.water_level.value_m == truth.water_level_m and proj.section.alpha == truth.alpha
    gcp = np.array(proj.ortho.gcp_px)
    err = np.linalg.norm(gcp - truth.gcp_px, axis=1)
    assert np.all(err < 1.5) and np.any(err > 0)  # a small seeded click error, not zero
    np.testing.assert_allclose(proj.ortho.distances_m, gcp_distances(truth.gcp_world_m), atol=1e-4)
    np.testing.assert_allclose(proj.section.points_px, truth.section_px, atol=1e-3)
    x0, y0, x1, y1 = proj.roi.rect_px
    assert 0 <= x0 < x1 <= spec.camera.width_px and 0 <= y0 < y1 <= spec.camera.height_px
    doc = json.loads(truth.truth_path.read_text())
    assert doc["discharge_m3s"] == pytest.approx(spec.river.truth()["discharge_m3s"])
    np.testing.assert_allclose(doc["camera"]["K"], spec.camera.K)


def test_shake_project_has_bank_regions_off_the_water(tmp_path):
    spec = presets.get("oblique", shake=True, duration_s=0.1)
    truth = render_scene(spec, tmp_path)
    proj = load_project(truth.project_path)
    assert proj.stabilize.enabled and len(proj.stabilize.regions_px) >= 2
    inv = np.linalg.inv(spec.camera.plane_homography(spec.river.level_m))
    for x0, y0, x1, y1 in proj.stabilize.regions_px:
        xs, ys = np.meshgrid(np.linspace(x0, x1, 15), np.linspace(y0, y1, 15))
        w = cv2.perspectiveTransform(np.column_stack([xs.ravel(), ys.ravel()]).reshape(-1, 1, 2), inv).reshape(-1, 2)
        assert np.all(np.abs(w[:, 1]) > spec.river.width_m / 2), "stable region touches the water"


def test_render_cancel(tmp_path):
    with pytest.raises(Cancelled):
        render_scene(presets.get("nadir", duration_s=0.2), tmp_path, cancel=lambda: True)


def test_checkerboard_video_corners_found(tmp_path):
    cam = presets.get("oblique", distortion=True).camera
    path = tmp_path / "cb.mp4"
    truth = render_checkerboard(cam, path, n_frames=10, seed=5)
    cap = cv2.VideoCapture(str(path))
    found, errs, i = 0, [], 0
    while True:
        ok, f = cap.read()
        if not ok:
            break
        g = cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)
        ok, c = cv2.findChessboardCorners(g, (9, 6))
        if ok:
            c = cv2.cornerSubPix(g, c, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3))
            c = c.reshape(-1, 2)
            t = truth["corners_px"][i]
            if np.linalg.norm(c[0] - t[0]) > np.linalg.norm(c[0] - t[-1]):  # board seen rotated by 180 degrees
                c = c[::-1]
            errs.append(np.abs(c - t).max())
            found += 1
        i += 1
    assert i == 10 and found >= 8
    assert max(errs) < 0.5  # the detected corners are where the known camera put them


def _target_centres(video, guess_px, start_offset=1.5):
    cap = cv2.VideoCapture(str(video))
    ok, f = cap.read()
    assert ok
    g = cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)
    pts = (np.asarray(guess_px, np.float32) + start_offset).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    return cv2.cornerSubPix(g, pts, (4, 4), (-1, -1), crit).reshape(-1, 2)


def test_rendered_targets_sit_on_projected_gcps(nadir_scene, tmp_path):
    # the checker targets' centres in frame 0 are where the camera model projects the GCPs
    _, truth, _, _ = nadir_scene
    np.testing.assert_allclose(_target_centres(truth.video_path, truth.gcp_px), truth.gcp_px, atol=0.25)
    dist = render_scene(presets.get("oblique", distortion=True, duration_s=0.1), tmp_path)
    near = [0, 1]  # the near-bank targets are big enough for a sub-pixel corner
    np.testing.assert_allclose(_target_centres(dist.video_path, dist.gcp_px[near]), dist.gcp_px[near], atol=0.3)
