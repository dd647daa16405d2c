"""Hard synthetic presets: each renders, its truth is the integral of the profile it draws, and the
difficulty it claims is really in the frames (glints flicker in place, ripples run upstream, the band
empties, the clip is fast, compressed, skewed, or has dropped frames with exact timestamps)."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest

from fieldtool.processing import piv
from fieldtool.processing.cross_section import load_cross_section
from fieldtool.processing.frames import FrameSource
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene

SHORT = {"duration_s": 0.2}
LONGER = {"dropped_frames": {"duration_s": 1.0}}  # enough frames for runs of dropped ones


def _frames(path) -> list[np.ndarray]:
    return [f.image for f in FrameSource(path)]


def _independent_q(river) -> float:
    """alpha * integral of u_s * d over the wetted width, by the trapezoidal rule on 400k points."""
    s = np.linspace(river.s_left, river.s_right, 400_001)
    return river.alpha * float(np.trapezoid(river.surface_velocity(s) * river.depth(s), s))


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = {}
    for name in presets.HARD_NAMES:
        spec = presets.get(name, **LONGER.get(name, SHORT))
        out[name] = (spec, render_scene(spec, tmp_path_factory.mktemp(name)))
    return out


@pytest.mark.parametrize("name", presets.HARD_NAMES)
def test_hard_preset_renders_with_drawn_truth(rendered, name):
    spec, truth = rendered[name]
    assert presets.get(name).duration_s == presets.HARD_DURATION_S  # 8 s unless overridden
    assert np.isfinite(truth.discharge_m3s) and truth.discharge_m3s > 0
    assert truth.discharge_m3s == pytest.approx(_independent_q(spec.river), rel=1e-6)
    doc = json.loads(truth.truth_path.read_text())
    assert doc["discharge_m3s"] == truth.discharge_m3s and doc["scene"] == name
    frames = _frames(truth.video_path)
    assert len(frames) == truth.n_frames >= 4
    assert frames[0].shape == (spec.camera.height_px, spec.camera.width_px)
    proj = load_project(truth.project_path)
    g = np.array(proj.ortho.gcp_px)
    assert np.all((g > 0) & (g < [spec.camera.width_px - 1, spec.camera.height_px - 1])), "GCPs must be in view"
    cs = load_cross_section(proj.resolve(proj.cross_section.path))
    skew = np.radians(spec.section_skew_deg)
    assert cs.wetted_width(spec.river.level_m) == pytest.approx(spec.river.width_m / np.cos(skew), rel=1e-5)


def test_hard_presets_deterministic_by_seed(tmp_path):
    def digest(seed, d):
        t = render_scene(presets.get("ripples", duration_s=0.1, seed=seed), tmp_path / d)
        return hashlib.md5(t.video_path.read_bytes()).hexdigest()

    assert digest(4, "a") == digest(4, "b")
    assert digest(4, "a") != digest(5, "c")


def _water_mask(spec, x_m, s_m):
    """Image mask (h, w) of the world rectangle X in x_m, stations (m from the left water edge) in s_m."""
    r = spec.river
    corners = [(x_m[0], s_m[0]), (x_m[1], s_m[0]), (x_m[1], s_m[1]), (x_m[0], s_m[1])]
    px = spec.camera.project(np.array([[x, r.y_left_edge - s, r.level_m] for x, s in corners]))
    m = np.zeros((spec.camera.height_px, spec.camera.width_px), np.uint8)
    cv2.fillConvexPoly(m, np.rint(px).astype(np.int32), 1)
    return m.astype(bool)


def test_glints_flicker_in_place_over_faint_tracers(rendered):
    spec, truth = rendered["glints_section"]
    frames = np.array(_frames(truth.video_path), np.float32)
    box = frames[:, _water_mask(spec, (-1.2, 1.2), (0.25 * 12, 0.75 * 12))]
    hi = box.max(axis=0) > 200
    assert hi.sum() > 200  # saturating glints on the section ...
    assert np.mean(box.min(axis=0)[hi] < 120) > 0.5  # ... that go dark in some frame: flicker in place
    # tracers away from the glints: 15-25 grey levels above the water (sensor noise sd 2 on top)
    q = frames[:, _water_mask(spec, (-3.0, -2.0), (1.0, 2.0))]
    contrast = np.percentile(q, 99.9) - np.median(q)
    assert 12 < contrast < 32


def test_ripples_run_upstream_where_the_flow_is_slow(rendered):
    spec, truth = rendered["ripples"]
    frames = np.array(_frames(truth.video_path), np.float64)
    r = spec.river
    c = spec.camera.project(np.array([[0.0, r.y_left_edge - 0.6, r.level_m], [1.0, r.y_left_edge - 0.6, r.level_m]]))
    down = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])  # image direction of the flow
    cx, cy = np.rint(c[0]).astype(int)
    half = 24
    patch = frames[:, cy - half : cy + half, cx - half : cx + half]
    win = cv2.createHanningWindow((2 * half, 2 * half), cv2.CV_64F)
    shifts = np.array([cv2.phaseCorrelate(patch[i], patch[i + 1], win)[0] for i in range(len(patch) - 1)])
    along = shifts @ down
    u_px = r.surface_velocity_y(r.y_left_edge - 0.6) / spec.fps * np.linalg.norm(c[1] - c[0])
    assert np.median(along) < 0 < u_px  # the texture goes upstream while the water goes downstream


def test_patchy_band_empties(tmp_path):
    spec = presets.get("sparse_patchy", duration_s=0.5, empty_after_s=0.1)
    truth = render_scene(spec, tmp_path)
    frames = _frames(truth.video_path)
    band = _water_mask(spec, (-2.0, 2.0), (0.3, 2.7))
    first, last = frames[0][band], frames[-1][band]
    assert (first > 90).sum() > 20  # tracers in the band at the start ...
    assert (last > 90).sum() == 0  # ... none once it emptied
    assert (
        frames[-1][_water_mask(spec, (-2.0, 2.0), (5.0, 11.0))] > 90
    ).sum() > 20  # the rest of the river still carries some


def test_fast_grazing_compressed_skewed_geometry(rendered, tmp_path):
    spec, truth = rendered["fast_1080p"]
    assert (spec.camera.width_px, spec.camera.height_px) == (1920, 1080) and spec.river.u_max_ms == 3.2
    assert 18.0 < max(truth.section_motion_px) < 26.0  # ~22 px/frame near the camera

    spec, _ = rendered["grazing"]
    r, cam = spec.river, spec.camera
    assert cam.position_m[2] - r.level_m == pytest.approx(2.0) and r.width_m == 25.0
    far = np.hypot(cam.position_m[1] - r.y_right_edge, cam.position_m[0] - r.x_section_m)
    assert np.degrees(np.arctan2(2.0, far)) < 5.0

    spec, truth = rendered["compressed"]
    clean = render_scene(spec.with_(jpeg_quality=0), tmp_path / "clean")
    a, b = (np.array(_frames(p), np.float32) for p in (truth.video_path, clean.video_path))
    assert np.sqrt(np.mean((a - b) ** 2)) > 1.0  # JPEG q12 artefacts on top of the codec's

    spec, truth = rendered["skewed"]
    inv = np.linalg.inv(spec.camera.plane_homography(spec.river.level_m))
    ends = cv2.perspectiveTransform(truth.section_px.reshape(-1, 1, 2), inv).reshape(-1, 2)
    d = ends[0] - ends[1]
    assert np.degrees(np.arctan2(abs(d[0]), abs(d[1]))) == pytest.approx(25.0, abs=1e-6)


def test_dropped_frames_timestamps_reach_the_piv(rendered):
    spec, truth = rendered["dropped_frames"]
    doc = json.loads(truth.truth_path.read_text())
    want = np.array(doc["frame_times_s"])
    got = np.array([f.t_s for f in FrameSource(truth.video_path)])
    assert len(got) == len(want) == truth.n_frames < spec.n_frames  # frames were dropped
    np.testing.assert_allclose(got, want, atol=2e-5)  # the container's timestamps, read back
    gaps = np.diff(want) * spec.fps
    assert gaps.max() > 1.9 and np.ptp(gaps) > 0.5  # variable frame rate
    res = piv.analyze(
        [(f.t_s, f.image) for f in FrameSource(truth.video_path)],
        piv.PivParams(window_px=32, overlap_px=16, passes=1, averaging="median"),
        roi=(400, 200, 720, 440),
    )
    np.testing.assert_allclose(res.dt_s, np.diff(want), atol=2e-5)
