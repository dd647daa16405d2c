"""The six thesis filters, background subtraction and the stack from the project file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldtool.errors import Cancelled, ParameterError
from fieldtool.processing.filters import FILTERS, FilterStack, noise_sigma, preview


def _image(seed=0, h=96, w=128) -> np.ndarray:
    """Dim, low-contrast water with a few bright particles (uint8)."""
    rng = np.random.default_rng(seed)
    base = 60 + 25 * cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 3)
    yy, xx = np.mgrid[0:h, 0:w]
    for x, y in rng.uniform(5, [w - 5, h - 5], (25, 2)):
        base += 150 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 3.0)
    return np.clip(base, 0, 255).astype(np.uint8)


def test_names():
    assert set(FILTERS) == {"highpass", "capping", "clahe", "brightness_contrast", "gamma", "nlmeans", "background"}


def test_capping_default_is_median_plus_two_sd():
    img = _image()
    limit = float(np.median(img) + 2 * img.astype(np.float64).std())
    stack = FilterStack.from_config([{"name": "capping"}])
    out = stack.apply(img)
    assert out.dtype == np.float32
    assert out.max() == pytest.approx(limit, abs=1e-3)
    below = img < limit
    np.testing.assert_array_equal(out[below], img[below])
    assert stack.resolved() == [{"name": "capping", "limit": pytest.approx(limit, abs=1e-3)}]
    # given value overrides
    assert FilterStack.from_config([{"name": "capping", "limit": 80}]).apply(img).max() == 80


def test_clahe_uses_opencv_defaults():
    img = _image(1)
    ref = cv2.createCLAHE().apply(img)  # clipLimit 40, 8 x 8 tiles
    np.testing.assert_array_equal(FilterStack.from_config([{"name": "clahe"}]).apply(img), ref)
    ref2 = cv2.createCLAHE(2.0, (4, 4)).apply(img)
    out2 = FilterStack.from_config([{"name": "clahe", "clip_limit": 2.0, "tile_grid": 4}]).apply(img)
    np.testing.assert_array_equal(out2, ref2)


def test_highpass_flattens_background_and_scales_to_full_range():
    img = _image(2).astype(np.float32)
    h, w = img.shape
    ramp = np.tile(np.linspace(0, 60, w, dtype=np.float32), (h, 1))  # slow illumination gradient
    out = FilterStack.from_config([{"name": "highpass"}]).apply(np.clip(img + ramp, 0, 255))
    assert out.max() == pytest.approx(255.0, abs=1e-3)  # factor = 255 / max
    # the gradient is gone: left and right thirds have the same median
    assert abs(np.median(out[:, : w // 3]) - np.median(out[:, -w // 3 :])) < 3
    with pytest.raises(ParameterError, match=r"filters\[0\].kernel_px: 16 must be odd"):
        FilterStack.from_config([{"name": "highpass", "kernel_px": 16}])


def test_brightness_contrast():
    img = _image(3)
    out = FilterStack.from_config([{"name": "brightness_contrast", "alpha": 1.3, "beta": 40}]).apply(img)
    np.testing.assert_allclose(out, np.clip(1.3 * img.astype(np.float32) + 40, 0, 255), atol=1e-4)
    auto = FilterStack.from_config([{"name": "brightness_contrast"}]).apply(img)
    lo, hi = np.percentile(auto, [1, 99])
    assert lo == pytest.approx(0, abs=1.0) and hi == pytest.approx(255, abs=1.0)


def test_gamma():
    img = _image(4)
    out = FilterStack.from_config([{"name": "gamma", "gamma": 0.4}]).apply(img)
    np.testing.assert_allclose(out, (img / 255.0) ** 0.4 * 255, atol=1e-3)
    auto = FilterStack.from_config([{"name": "gamma"}])
    assert np.median(auto.apply(img)) == pytest.approx(127.5, abs=1.0)  # median grey -> mid-grey
    assert auto.resolved()[0]["gamma"] < 1  # the dim image is brightened


def test_nlmeans_strength_from_noise_and_denoises():
    rng = np.random.default_rng(5)
    clean = np.tile(np.linspace(80, 160, 128, dtype=np.float32), (96, 1))
    noisy = np.clip(clean + rng.normal(0, 10, clean.shape), 0, 255).astype(np.uint8)
    assert noise_sigma(noisy) == pytest.approx(10, rel=0.15)
    stack = FilterStack.from_config([{"name": "nlmeans"}])
    out = stack.apply(noisy)
    assert stack.resolved()[0]["h"] == pytest.approx(noise_sigma(noisy), rel=1e-6)
    assert np.abs(out - clean).mean() < 0.5 * np.abs(noisy - clean).mean()
    with pytest.raises(ParameterError, match=r"filters\[0\].search_px: 5 px is smaller than template_px"):
        FilterStack.from_config([{"name": "nlmeans", "search_px": 5}])


def _glint_clip(n=24, shift=3, seed=6, h=96, w=128):
    """Texture moving `shift` px/frame to the right under strong static glints."""
    rng = np.random.default_rng(seed)
    tex = 100 + 40 * cv2.GaussianBlur(rng.standard_normal((h, w + shift * n)).astype(np.float32), (0, 0), 1.5)
    yy, xx = np.mgrid[0:h, 0:w]
    glint = np.zeros((h, w), np.float32)
    for x, y in [(30, 30), (90, 60), (60, 20), (100, 25), (20, 75)]:
        glint += 255 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 6.0**2))
    frames = []
    for t in range(n):
        x0 = shift * (n - t)  # content moves right as t grows
        frames.append(np.clip(tex[:, x0 : x0 + w] + glint, 0, 255).astype(np.uint8))
    return frames


def _displacement(a: np.ndarray, b: np.ndarray) -> tuple[int, int]:
    """Integer shift of b relative to a from the peak of the FFT cross-correlation."""
    a = a - a.mean()
    b = b - b.mean()
    c = np.fft.irfft2(np.conj(np.fft.rfft2(a)) * np.fft.rfft2(b), s=a.shape)
    dy, dx = np.unravel_index(np.argmax(c), c.shape)
    h, w = a.shape
    return int((dx + w // 2) % w - w // 2), int((dy + h // 2) % h - h // 2)


@pytest.mark.parametrize("method", ["mean", "median"])
def test_background_subtraction_removes_static_glints(method):
    frames = _glint_clip()
    assert _displacement(frames[10].astype(np.float32), frames[11].astype(np.float32)) == (0, 0)  # glints win
    stack = FilterStack.from_config([{"name": "background", "method": method, "samples": 9}])
    assert stack.needs_prepass
    with pytest.raises(RuntimeError, match="prepass"):
        stack.apply(frames[0])
    stack.prepass(iter(frames))
    a, b = stack.apply(frames[10]), stack.apply(frames[11])
    assert _displacement(a, b) == (3, 0)  # the true motion
    glint_px = (slice(24, 36), slice(24, 36))
    assert abs(float(np.mean(a[glint_px])) - 127.5) < 20  # the glint is gone, "no difference" grey


def test_prepass_cancel():
    stack = FilterStack.from_config([{"name": "background"}])
    with pytest.raises(Cancelled):
        stack.prepass(_glint_clip(n=4), cancel=lambda: True)


def test_background_after_other_filters_uses_their_output():
    frames = _glint_clip(n=8)
    stack = FilterStack.from_config([{"name": "gamma", "gamma": 2.0}, {"name": "background", "offset": 0}])
    stack.prepass(frames)
    g = [((f / 255.0) ** 2.0 * 255).astype(np.float32) for f in frames]
    expected = np.clip(g[3] - np.mean(g, axis=0), 0, 255)
    np.testing.assert_allclose(stack.apply(frames[3]), expected, atol=1e-3)


def test_image_defaults_are_kept_for_the_whole_clip():
    a, b = _image(7), _image(8)
    stack = FilterStack.from_config([{"name": "capping"}])
    stack.apply(a)
    limit = stack.resolved()[0]["limit"]
    assert stack.apply(b).max() <= limit + 1e-4
    assert FilterStack.from_config([{"name": "capping"}]).resolved() == [{"name": "capping", "limit": None}]


def test_stack_order_matters():
    img = _image(9)
    one = FilterStack.from_config([{"name": "capping", "limit": 100}, {"name": "gamma", "gamma": 0.5}]).apply(img)
    two = FilterStack.from_config([{"name": "gamma", "gamma": 0.5}, {"name": "capping", "limit": 100}]).apply(img)
    assert one.max() == pytest.approx((100 / 255) ** 0.5 * 255, abs=1e-3)
    assert two.max() == pytest.approx(100, abs=1e-3)


def test_config_errors_name_the_key():
    with pytest.raises(ParameterError, match=r"filters\[2\].gamma: 0 is out of range; use 0 < gamma <= 10"):
        FilterStack.from_config([{"name": "clahe"}, {"name": "capping"}, {"name": "gamma", "gamma": 0}])
    with pytest.raises(ParameterError, match=r"filters\[1\].name: unknown filter 'blur'"):
        FilterStack.from_config([{"name": "clahe"}, {"name": "blur"}])
    with pytest.raises(ParameterError, match=r"filters\[0\].sigma: unknown parameter for the clahe filter"):
        FilterStack.from_config([{"name": "clahe", "sigma": 2}])
    with pytest.raises(ParameterError, match=r"filters\[0\].clip_limit: expected a number"):
        FilterStack.from_config([{"name": "clahe", "clip_limit": "high"}])
    with pytest.raises(ParameterError, match=r"filters\[0\].tile_grid: expected a whole number"):
        FilterStack.from_config([{"name": "clahe", "tile_grid": 2.5}])
    with pytest.raises(ParameterError, match=r"filters\[0\].alpha: 11 is out of range"):
        FilterStack.from_config([{"name": "brightness_contrast", "alpha": 11}])
    with pytest.raises(ParameterError, match=r"filters\[0\].method: 'mode' is not allowed"):
        FilterStack.from_config([{"name": "background", "method": "mode"}])
    with pytest.raises(ParameterError, match=r"filters\[1\]: background subtraction is already in the stack"):
        FilterStack.from_config([{"name": "background"}, {"name": "background"}])
    with pytest.raises(ParameterError, match=r"filters\[0\]: expected a table"):
        FilterStack.from_config(["clahe"])


def test_preview():
    img = _image(10)
    png = preview([{"name": "clahe", "clip_limit": 2.0}, {"name": "gamma", "gamma": 1.5}], img)
    assert png.dtype == np.uint8 and png.shape == img.shape
    ok, buf = cv2.imencode(".png", png)
    assert ok and len(buf) > 0
    assert np.array_equal(preview([], img), img)
    with pytest.raises(ParameterError, match="needs the clip"):
        preview([{"name": "background"}], img)
    frames = _glint_clip(n=6)
    assert preview([{"name": "background"}], frames[2], frames=frames).dtype == np.uint8


def test_filters_work_inside_the_roi_only():
    """Thesis 9.2.7 / PIVlab: a bright sky outside the ROI must not set the capping limit or the
    high-pass gain; outside the ROI the frame is left as it was."""
    from fieldtool.processing.filters import FilterStack

    rng = np.random.default_rng(0)
    img = np.full((120, 160), 40.0, np.float32) + rng.normal(0, 5, (120, 160)).astype(np.float32)
    img[:40] = 250.0  # sky
    roi = (20, 60, 140, 110)
    items = [{"name": "capping"}, {"name": "highpass", "kernel_px": 7}]
    whole = FilterStack.from_config(items)
    whole.apply(img)
    inside = FilterStack.from_config(items, roi=roi)
    out = inside.apply(img)
    crop_only = FilterStack.from_config(items)
    ref = crop_only.apply(img[60:110, 20:140].copy())
    np.testing.assert_allclose(out[60:110, 20:140], ref)
    np.testing.assert_array_equal(out[:60], img[:60])
    lim_roi, lim_whole = inside.resolved()[0]["limit"], whole.resolved()[0]["limit"]
    assert lim_roi < 70 < lim_whole  # the sky raised the whole-frame limit far above the water's
