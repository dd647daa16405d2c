"""Removal of what is not advected by the flow before PIV: a streaming, flicker-robust temporal standardisation.

Sun glints that flicker in place, standing waves, haze and the banks form patterns fixed in the image. Their
correlation peak sits at zero displacement and can beat the tracers' peak (a glint is 10x brighter than a
natural tracer). Each frame is replaced, inside a box around the ROI, by

    (I_t(p) - mean_W(p)) / (std_W(p) + std_ref)

where mean_W and std_W are the pixel's mean and standard deviation over a centred window of ``2 * half + 1``
frames (clamped at the clip's ends) and ``std_ref`` is the median of std_W over the box. Subtracting the mean
removes what is fixed; a pattern that flickers in place independently from frame to frame keeps no correlation
at zero displacement once its mean is gone (E[(L_a - p)(L_b - p)] = 0), and dividing by the pixel's own
temporal spread brings specular pixels (bright, short-lived, not advected) down to the tracers' level, so they
no longer dominate their windows. Moving tracers pass through a pixel in a few frames, far fewer than the
window, so they keep their contrast.

The stream holds ``2 * half + 1`` crops of the box (float16) and running sums: memory is bounded whatever the
clip length, and frames come out in order, ``half`` frames after they went in.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Iterable, Iterator

import cv2
import numpy as np

#: frames on each side of the centred window (30 fps: about 1 s in all)
HALF_WINDOW = 15
#: soft threshold in robust standard deviations of the standardised frame
SHRINK = 3.0
SHRINK_MODE = "soft"
#: Gaussian smoothing (px) of the spread map: a gain with pixel-scale structure would be a fixed pattern of its own
GAIN_BLUR_PX = 0.0
#: window rms (standardised units) below which PIV treats a window as featureless (PivParams.min_texture)
MIN_TEXTURE = 0.05


@dataclass
class SurfaceStats:
    """What the standardisation saw, for the run's report."""

    frames: int = 0
    box: tuple[int, int, int, int] | None = None  # (x0, y0, x1, y1) processed, px
    std_ref: float = float("nan")  # median temporal standard deviation over the box (grey levels)
    specular_fraction: float = float("nan")  # share of box pixels whose spread exceeds 4 x std_ref (glints)


def _box(shape: tuple[int, int], roi, margin: int) -> tuple[int, int, int, int]:
    h, w = shape
    if roi is None:
        return 0, 0, w, h
    x0, y0, x1, y1 = (int(round(float(c))) for c in roi)
    return max(min(x0, x1) - margin, 0), max(min(y0, y1) - margin, 0), min(max(x0, x1) + margin, w), min(max(y0, y1) + margin, h)


def standardize(frames: Iterable[tuple[float, np.ndarray]], roi=None, *, margin: int = 64, half: int = HALF_WINDOW,
                shrink: float = SHRINK, stats: SurfaceStats | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """Stream (t_s, float32 frame) standardised over time inside the ROI box.

    Parameters
    ----------
    frames : iterable of (t_s, gray image HxW); consumed once.
    roi : (x0, y0, x1, y1) px or None (whole frame); the box processed is the ROI grown by ``margin`` px
        (the first PIV pass' search area reaches outside the ROI). Pixels outside the box are 0.
    half : frames on each side of the centred window (>= 1).
    shrink : soft threshold, in robust standard deviations of the standardised frame (0 = off): values within
        +-shrink * 1.4826 * median|z| become 0 and the others move towards 0 by that much. What is left is the
        sparse, strong texture of tracers; a dense, weak, Gaussian-like texture (wind ripples, codec and sensor
        noise) goes, and windows with nothing else become featureless (see ``PivParams.min_texture``).
    stats : filled with what was seen (see :class:`SurfaceStats`).

    Yields
    ------
    (t_s, float32 image), zero mean and unit-ish spread per pixel; same times and order as the input.
    """
    it = iter(frames)
    n_win = 2 * half + 1
    buf: deque = deque()
    times: deque = deque()
    st = _Sums()
    box = None
    shape = None
    ref = None
    static = [False]

    def push(t, img):
        nonlocal box, shape
        a = np.asarray(img)
        if box is None:
            shape = a.shape
            box = _box(shape, roi, margin)
            if stats is not None:
                stats.box = box
        x0, y0, x1, y1 = box
        c = a[y0:y1, x0:x1].astype(np.float32)
        st.add(c)
        buf.append(c.astype(np.float16))
        times.append(float(t))

    def moments():
        nonlocal ref
        if st.updates >= _RESUM_EVERY:  # running float32 sums drift: recompute them from the window now and then
            st.reset(buf)
        mean, sd = st.moments(len(buf))
        if ref is None:  # the box's typical spread, from the first window
            med = float(np.median(sd))
            static[0] = med < 1e-3  # nothing moves or flickers: frames pass unchanged (PIV then sees no motion)
            ref = max(med, 1e-3)
            if stats is not None:
                stats.std_ref = ref
                stats.specular_fraction = float(np.mean(sd > 4.0 * ref))
        if GAIN_BLUR_PX > 0:
            sd = cv2.GaussianBlur(sd, (0, 0), GAIN_BLUR_PX)
        sd += ref
        return mean, sd

    def emit(c16: np.ndarray, t: float, mean: np.ndarray, den: np.ndarray):
        out = np.zeros(shape, np.float32)
        x0, y0, x1, y1 = box
        o = out[y0:y1, x0:x1]
        if static[0]:
            o[:] = c16
            if stats is not None:
                stats.frames += 1
            return t, out
        np.subtract(c16, mean, out=o, dtype=np.float32)
        o /= den
        if shrink > 0:
            tau = np.float32(shrink * 1.4826 * np.median(np.abs(o[::4, ::4])))
            if SHRINK_MODE == "hard":
                o[np.abs(o) < tau] = 0.0
            else:
                mag = np.abs(o)
                mag -= tau
                np.maximum(mag, 0.0, out=mag)
                np.copysign(mag, o, out=o)
        if stats is not None:
            stats.frames += 1
        return t, out

    for t, img in it:  # fill the first window
        push(t, img)
        if len(buf) == n_win:
            break
    if not buf:
        return
    mean, den = moments()
    centre = min(half, len(buf) - 1)
    for k in range(centre + 1):  # the first frames use the first full window
        yield emit(buf[k], times[k], mean, den)
    for t, img in it:
        st.remove(buf.popleft())
        times.popleft()
        push(t, img)
        mean, den = moments()
        yield emit(buf[half], times[half], mean, den)
    start = half + 1 if len(buf) == n_win else centre + 1
    for j in range(start, len(buf)):  # the last frames use the last full window
        yield emit(buf[j], times[j], mean, den)


_RESUM_EVERY = 256


class _Sums:
    """Running per-pixel sums of I and I² over the window (float32, recomputed every ``_RESUM_EVERY`` updates)."""

    def __init__(self):
        self.s1 = self.s2 = self.tmp = None
        self.updates = 0

    def add(self, c: np.ndarray) -> None:
        if self.s1 is None:
            self.s1, self.s2, self.tmp = (np.zeros_like(c) for _ in range(3))
        self.s1 += c
        np.multiply(c, c, out=self.tmp)
        self.s2 += self.tmp
        self.updates += 1

    def remove(self, c16: np.ndarray) -> None:
        np.subtract(self.s1, c16, out=self.s1)
        np.multiply(c16, c16, out=self.tmp, dtype=np.float32)
        self.s2 -= self.tmp
        self.updates += 1

    def reset(self, buf) -> None:
        self.s1[:] = 0
        self.s2[:] = 0
        for c16 in buf:
            self.s1 += c16
            np.multiply(c16, c16, out=self.tmp, dtype=np.float32)
            self.s2 += self.tmp
        self.updates = 0

    def moments(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        mean = self.s1 * np.float32(1.0 / n)
        var = self.s2 * np.float32(1.0 / n)
        np.multiply(mean, mean, out=self.tmp)
        var -= self.tmp
        np.maximum(var, 0.0, out=var)
        return mean, np.sqrt(var, out=var)
