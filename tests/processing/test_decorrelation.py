"""The water's decorrelation time from the first frames, and the frame step it asks for."""

import cv2
import numpy as np
import pytest

from fieldtool.processing import decorrelation


def moving_pattern(speed_px: float, n: int = 20, size_px: float = 3.0, noise: float = 0.0, seed: int = 0):
    """``n`` frames of a blurred random pattern (blobs of about ``size_px``) moving ``speed_px`` a frame along x,
    with white noise of ``noise`` times the pattern's spread."""
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.normal(size=(96, 96 + int(speed_px * n) + 8)).astype(np.float32), (0, 0), size_px)
    big /= big.std()
    xs = np.arange(96, dtype=np.float32)
    frames = []
    for t in range(n):
        mx, my = np.meshgrid(xs + 4 + speed_px * t, xs)
        f = cv2.remap(big, mx, my, cv2.INTER_LINEAR)
        frames.append(f + noise * rng.normal(size=f.shape).astype(np.float32))
    return np.stack(frames)


def test_the_time_scales_with_the_speed():
    """A quarter of the speed, four times the frames to change (the same pattern): the fit is of the motion,
    not of the few frames looked at (whose mean it models)."""
    fast = decorrelation.fit(moving_pattern(2.0))
    slow = decorrelation.fit(moving_pattern(0.5))
    assert fast is not None and slow is not None
    assert fast.share > 0.9 and slow.share > 0.9
    assert slow.tau_frames / fast.tau_frames == pytest.approx(4.0, rel=0.25)
    assert decorrelation.step_for(fast, 300, 31) == 1
    assert decorrelation.step_for(slow, 300, 31) == int(slow.tau_frames // decorrelation.TAU_FRAMES) > 1


def test_noise_is_not_a_pattern():
    """White noise (sensor noise, one-frame glints) has no persistent share: no step, whatever its fitted
    time; a faint moving pattern under noise keeps its time."""
    rng = np.random.default_rng(1)
    white = decorrelation.fit(rng.normal(size=(20, 64, 64)).astype(np.float32))
    assert white is not None and white.share < decorrelation.MIN_SHARE
    assert decorrelation.step_for(white, 1000, 31) == 1
    slow = decorrelation.fit(moving_pattern(0.5, noise=0.5))
    clean = decorrelation.fit(moving_pattern(0.5))
    assert slow is not None and clean is not None and 0.5 < slow.share < clean.share
    assert slow.tau_frames == pytest.approx(clean.tau_frames, rel=0.2)


def test_the_step_keeps_enough_frames():
    slow = decorrelation.fit(moving_pattern(0.25))
    assert slow is not None and decorrelation.step_for(slow, 0, 31) >= 4
    assert decorrelation.step_for(slow, 100, 31) == 3  # 100 frames keep 31 at a step of 3
    assert decorrelation.step_for(slow, 40, 31) == 1
    assert decorrelation.fit(np.zeros((20, 8, 8), np.float32)) is None  # nothing changes at all
    assert decorrelation.fit(np.zeros((3, 8, 8), np.float32)) is None  # too few frames


def test_an_exposure_or_a_fade_is_not_the_pattern_changing():
    """Every pixel's gain and offset changing together (a phone's exposure settling over the first frames, a
    fade from black) leaves the fitted time and step of the pattern as they were: on a fast pattern, no step."""
    fast = moving_pattern(2.0) + 4.0  # a background: the frames are brightness, not a residual
    gain = 1.0 + 1.2 * np.exp(-np.arange(20) / 6.0)[:, None, None]
    fade = np.minimum(np.arange(20) / 10.0, 1.0)[:, None, None] + 0.05
    plain = decorrelation.fit(fast)
    assert plain is not None and decorrelation.step_for(plain, 300, 31) == 1
    for changed in (fast * gain + 30.0 * (gain - 1.0), fast * fade):
        d = decorrelation.fit(changed)
        assert d is not None and d.tau_frames == pytest.approx(plain.tau_frames, rel=0.15)
        assert decorrelation.step_for(d, 300, 31) == 1
