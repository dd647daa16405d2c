"""Stabilisation on small synthetic scenes with a known camera motion and a known flow."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldtool.errors import GeometryError, ParameterError
from fieldtool.processing.stabilize import Stabilizer

H, W = 240, 400
BAND = (80, 160)  # water rows
BANKS = [[10, 10, 190, 70], [210, 10, 390, 70], [10, 170, 190, 230], [210, 170, 390, 230]]
ON_WATER = [[20, 90, 190, 150], [210, 90, 380, 150]]
WATER_POLYGON = [[-0.5, 78], [399.5, 78], [399.5, 162], [-0.5, 162]]


def _texture(h, w, rng, sigma):
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    return 40 + 180 * (t - t.min()) / (t.max() - t.min())


def _scene(n=15, flow=3, shake=5.0, rot_deg=0.6, seed=0, renew_water=False, drift=(0.0, 0.0)):
    """Frames of banks + a water band flowing ``flow`` px/frame to the right, seen by a shaking camera
    whose view also drifts ``drift`` px/frame.

    Returns (frames uint8, true scenes float32, affine maps scene -> frame). Frame 0 is unshaken.
    """
    rng = np.random.default_rng(seed)
    bank = _texture(H, W, rng, 1.5)
    water = _texture(H, W + flow * n + 10, rng, 2.0)
    frames, scenes, maps = [], [], []
    for t in range(n):
        s = bank.copy()
        if renew_water:  # a real surface: the pattern changes from frame to frame
            s[BAND[0] : BAND[1]] = _texture(BAND[1] - BAND[0], W, rng, 2.0)
        else:
            x0 = flow * (n - t)
            s[BAND[0] : BAND[1]] = water[BAND[0] : BAND[1], x0 : x0 + W]
        M = np.eye(2, 3)
        if t:
            M = cv2.getRotationMatrix2D((W / 2, H / 2), rng.uniform(-rot_deg, rot_deg), 1.0)
            M[:, 2] += rng.uniform(-shake, shake, 2) + np.asarray(drift) * t
        frames.append(
            cv2.warpAffine(s, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.uint8)
        )
        scenes.append(s)
        maps.append(np.vstack([M, [0, 0, 1]]))
    return frames, scenes, maps


def _shift(a, b):
    """Sub-pixel (dx, dy) of b relative to a (phase correlation, Hann window)."""
    win = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64), win)
    return dx, dy


@pytest.mark.parametrize("model", ["homography", "affine"])
def test_recovers_the_camera_motion(model):
    frames, scenes, maps = _scene()
    st = Stabilizer(frames[0], regions_px=BANKS, model=model)
    corners = np.array([[[0.0, 0.0]], [[W - 1.0, 0.0]], [[0.0, H - 1.0]], [[W - 1.0, H - 1.0]]])
    for f, s, M in zip(frames, scenes, maps, strict=True):
        out = st.register(f)
        assert out.shape == f.shape and out.dtype == f.dtype
        # registration composed with the true motion is the identity, to a tenth of a pixel
        back = cv2.perspectiveTransform(corners, st.transform @ M)
        assert np.abs(back - corners).max() < 0.1
        rows = np.r_[15:65, 175:225]
        assert np.abs(out[rows, 15:-15].astype(float) - s[rows, 15:-15]).mean() < 3.0
    rep = st.report()
    assert rep["frames"] == len(frames)
    assert rep["median_px"] < 0.05 and rep["max_px"] < 2.0  # max: worst single feature, within RANSAC's 2 px
    assert rep["max_shift_px"] > 3.0


def test_water_keeps_its_own_motion():
    frames, _, _ = _scene(flow=3, shake=5.0)
    st = Stabilizer(frames[0], regions_px=BANKS)
    reg = [st.register(f) for f in frames]
    band = slice(BAND[0] + 10, BAND[1] - 10)
    raw = [_shift(frames[k][band], frames[k + 1][band])[0] for k in range(1, 10)]
    fixed = [_shift(reg[k][band], reg[k + 1][band])[0] for k in range(1, 10)]
    assert np.abs(np.array(fixed) - 3.0).max() < 0.2  # the true flow, frame after frame
    assert np.abs(np.array(raw) - 3.0).max() > 2.0  # without stabilisation the shake is in the flow


def test_water_polygon_instead_of_regions():
    frames, _, maps = _scene(seed=3)
    st = Stabilizer(frames[0], water_polygon_px=WATER_POLYGON)
    corners = np.array([[[0.0, 0.0]], [[W - 1.0, H - 1.0]]])
    for f, M in zip(frames, maps, strict=True):
        st.register(f)
        assert np.abs(cv2.perspectiveTransform(corners, st.transform @ M) - corners).max() < 0.1


@pytest.mark.parametrize("water_box", [None, (0, BAND[0] - 5, W, BAND[1] + 5)])
def test_regions_on_moving_water_drift_error(water_box):
    """Also where the vote leaves the water's box out: the banks that stayed put still testify."""
    frames, _, _ = _scene(n=40, flow=5, shake=3.0)
    st = Stabilizer(frames[0], regions_px=ON_WATER, water_box_px=water_box)
    with pytest.raises(GeometryError, match="drifted .* steadily .* rest of the picture stayed put"):
        for f in frames:
            st.register(f)


def test_drifting_camera_is_not_taken_for_water():
    """A hovering drone drifts steadily too, but it moves the whole picture, not just the regions."""
    frames, _, maps = _scene(n=40, flow=5, shake=2.0, drift=(1.5, 0.8))
    st = Stabilizer(frames[0], regions_px=BANKS)
    corners = np.array([[[0.0, 0.0]], [[W - 1.0, H - 1.0]]])
    for f, M in zip(frames, maps, strict=True):
        st.register(f)
        assert np.abs(cv2.perspectiveTransform(corners, st.transform @ M) - corners).max() < 0.5
    assert st.report()["max_shift_px"] > 2 * st.max_drift_px  # the check ran, and let it pass


def test_glitter_that_stays_in_the_picture_is_not_taken_for_fixed_ground():
    """Sun glitter (and the sky's reflection) stays where it is in the picture when the camera moves: over a
    drifting camera's water band it outvotes the banks, as if the regions had drifted on water; the water's box
    (the run passes the PIV's ROI) is left out of the vote, and the drift is followed."""
    frames, _, maps = _scene(n=40, flow=5, shake=2.0, drift=(1.5, 0.8))
    glitter = np.zeros((H, W), np.float32)
    glitter[BAND[0] : BAND[1]] = np.where(np.random.default_rng(7).random((BAND[1] - BAND[0], W)) > 0.7, 120, 0)
    glitter = cv2.GaussianBlur(glitter, (0, 0), 1.0)
    frames = [np.clip(f + glitter, 0, 255).astype(np.uint8) for f in frames]
    with pytest.raises(GeometryError, match="drifted .* steadily"):
        st = Stabilizer(frames[0], regions_px=BANKS)
        for f in frames:
            st.register(f)
    st = Stabilizer(frames[0], regions_px=BANKS, water_box_px=(0, BAND[0], W, BAND[1]))
    corners = np.array([[[0.0, 0.0]], [[W - 1.0, H - 1.0]]])
    for f, M in zip(frames, maps, strict=True):
        st.register(f)
        assert np.abs(cv2.perspectiveTransform(corners, st.transform @ M) - corners).max() < 0.5
    assert st.report()["max_shift_px"] > 2 * st.max_drift_px


def test_regions_on_changing_water_lost_error():
    frames, _, _ = _scene(n=6, renew_water=True)
    st = Stabilizer(frames[0], regions_px=ON_WATER)
    with pytest.raises(GeometryError, match="could be followed .* probably lie on water"):
        for f in frames:
            st.register(f)


def test_one_region_on_water_is_named():
    frames, _, _ = _scene(n=12, flow=4)
    regions = BANKS[:3] + [[250, 100, 330, 140]]  # the last one sits on the water
    st = Stabilizer(frames[0], regions_px=regions)
    with pytest.raises(GeometryError, match=r"stabilize.regions_px\[3\]: its features move differently"):
        for f in frames:
            st.register(f)


def test_bad_setup():
    frames, _, _ = _scene(n=2)
    with pytest.raises(ParameterError, match="give stable regions"):
        Stabilizer(frames[0])
    with pytest.raises(ParameterError, match=r"stabilize.regions_px\[1\]: .* reaches outside"):
        Stabilizer(frames[0], regions_px=[BANKS[0], [300, 10, 450, 60]])
    with pytest.raises(ParameterError, match="stabilize.model"):
        Stabilizer(frames[0], regions_px=BANKS, model="similarity")
    with pytest.raises(ParameterError, match="at least 3 points"):
        Stabilizer(frames[0], water_polygon_px=[[0, 0], [10, 10]])
    flat = np.full((H, W), 120, np.uint8)
    with pytest.raises(GeometryError, match="too small or too smooth"):
        Stabilizer(flat, regions_px=BANKS)
    st = Stabilizer(frames[0], regions_px=BANKS)
    with pytest.raises(ParameterError, match="differs from frame 0"):
        st.register(np.zeros((H + 2, W), np.uint8))
    assert st.report()["frames"] == 0


def test_exposure_that_pumps_keeps_the_features_and_the_drift_check():
    """A phone's auto-exposure: the gain swings by +-35 % while the camera drifts. The features are followed on
    the frames with their local mean and contrast out, and the whole-picture check matches the gain first."""
    frames, _, maps = _scene(n=40, flow=5, shake=2.0, drift=(1.5, 0.8))
    gain = 1.0 + 0.35 * np.sin(np.arange(len(frames)) / 3.0)
    frames = [np.clip(f * g + 10.0 * (g - 1.0), 0, 255).astype(np.uint8) for f, g in zip(frames, gain, strict=True)]
    st = Stabilizer(frames[0], regions_px=BANKS)
    corners = np.array([[[0.0, 0.0]], [[W - 1.0, H - 1.0]]])
    for f, M in zip(frames, maps, strict=True):
        st.register(f)
        assert np.abs(cv2.perspectiveTransform(corners, st.transform @ M) - corners).max() < 0.5
    assert st.report()["max_shift_px"] > 2 * st.max_drift_px
