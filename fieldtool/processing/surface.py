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

The stream holds ``2 * half + 1`` crops of the box (uint8 as decoded, else float32, float16 for a very large
box) and running sums: memory is bounded whatever the clip length, and frames come out in order, ``half``
frames after they went in.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from fieldtool.processing.framepool import FramePool, pool_cap

#: frames on each side of the centred window (30 fps: about 1 s in all)
HALF_WINDOW = 15
#: soft threshold in robust standard deviations of the standardised frame
SHRINK = 3.0
#: subtract the centred temporal mean once more after the threshold (see _recentre)
RECENTRE = True
#: window rms (standardised units) below which PIV treats a window as featureless (PivParams.min_texture)
MIN_TEXTURE = 0.05


@dataclass
class SurfaceStats:
    """What the standardisation saw, for the run's report."""

    frames: int = 0
    box: tuple[int, int, int, int] | None = None  # (x0, y0, x1, y1) processed, px
    std_ref: float = float("nan")  # median temporal standard deviation over the box (grey levels)
    specular_fraction: float = float("nan")  # share of box pixels whose spread exceeds 4 x std_ref (glints)
    static: bool = False  # nothing moves or flickers in the first window: frames passed unchanged (PIV sees no motion)
    shape: tuple[int, int] | None = None  # (H, W) of the frames, px


def _box(shape: tuple[int, int], roi, margin: int) -> tuple[int, int, int, int]:
    h, w = shape
    if roi is None:
        return 0, 0, w, h
    x0, y0, x1, y1 = (int(round(float(c))) for c in roi)
    return (
        max(min(x0, x1) - margin, 0),
        max(min(y0, y1) - margin, 0),
        min(max(x0, x1) + margin, w),
        min(max(y0, y1) + margin, h),
    )


#: px the processed box reaches beyond the ROI, at least (:func:`margin_for`)
MARGIN = 64


def margin_for(search_px: int | None) -> int:
    """px the standardisation's box reaches beyond the PIV's box: :data:`MARGIN`, or the first pass' search
    area (``PivParams.search_px``) where it is larger."""
    return max(MARGIN, int(search_px or 0))


def standardize(
    frames: Iterable[tuple[float, np.ndarray]],
    roi=None,
    *,
    margin: int = MARGIN,
    half: int = HALF_WINDOW,
    shrink: float = SHRINK,
    stats: SurfaceStats | None = None,
    want: Callable[[int], bool] | None = None,
) -> Iterator[tuple[float, np.ndarray | None]]:
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
    want : ``want(k)`` false: the frame at stream position k comes out as (t_s, None), not built (every frame
        still enters the running window; the fast path correlates only some pairs). None: every frame.

    Yields
    ------
    (t_s, float32 image), zero mean and unit-ish spread per pixel; same times and order as the input.
    """
    stats = stats if stats is not None else SurfaceStats()
    spare: list[np.ndarray] = []  # the recentring hands back the crops its window let go (:func:`_standardize`)
    crops = _standardize(frames, roi, margin=margin, half=half, shrink=shrink, stats=stats, spare=spare)
    if shrink > 0 and RECENTRE:
        return _recentre(crops, stats, half, want, spare)
    return _frames(crops, stats, want)


def _frames(crops: Iterator[tuple[float, np.ndarray]], stats: SurfaceStats, want) -> Iterator:
    """Whole frames (0 outside the box, read-only, recycled: :class:`FramePool`) from the box crops."""
    pool = None
    for k, (t, c) in enumerate(crops):
        if want is not None and not want(k):
            yield t, None
            continue
        assert stats.shape is not None and stats.box is not None  # set from the first frame, before any crop
        pool = pool or FramePool(stats.shape, pool_cap(stats.shape, stats.box))
        yield t, pool.filled(stats.box, lambda v, c=c: np.copyto(v, c))


#: the window's crops are kept as float32 while a window of them stays under this many bytes; float16 above
#: (a whole 4K frame: 31 float32 crops would take 1 GB)
WINDOW_BYTES_F32 = 160 * 2**20


def _window_dtype(box: tuple[int, int, int, int], n_win: int):
    x0, y0, x1, y1 = box
    return np.float32 if (x1 - x0) * (y1 - y0) * n_win * 4 <= WINDOW_BYTES_F32 else np.float16


def _stored(c: np.ndarray, dtype) -> np.ndarray:
    """``c`` (a fresh crop) as the window keeps it: itself (uint8 frames: exact in a quarter of float32's
    memory; float32), or rounded to float16."""
    return c if dtype is np.float32 or c.dtype == np.uint8 else c.astype(np.float16)


def _recentre(
    frames: Iterator[tuple[float, np.ndarray]], stats: SurfaceStats, half: int, want=None, spare: list | None = None
):
    """Subtract each pixel's centred temporal mean again, after the soft threshold: the threshold is not
    linear, and a pattern that flickers in place between two levels would otherwise come back with a mean of
    its own (E[(z_a)(z_b)] > 0 at zero displacement). ``frames`` are the box crops of :func:`_standardize`;
    each crop the window lets go is handed back to ``spare``, where :func:`_standardize` writes a later one
    (a fresh crop would cost its pages again)."""
    n_win = 2 * half + 1
    buf: deque = deque()
    times: deque = deque()
    st = _Sums(squares=False)
    dtype = None
    k_out = 0
    pool: FramePool | None = None

    def push(t, c):
        nonlocal dtype
        if dtype is None:
            dtype = _window_dtype(stats.box, n_win)
        st.add(c)
        kept = _stored(c, dtype)
        buf.append(kept)
        times.append(t)
        if kept is not c and spare is not None:  # rounded to float16: the crop itself is free at once
            spare.append(c)

    def pop():
        old = buf.popleft()
        st.remove(old)
        times.popleft()
        if spare is not None and old.dtype == np.float32:
            spare.append(old)

    def emit(c16, t):
        nonlocal k_out, pool
        if st.updates >= _RESUM_EVERY:
            st.reset(buf)
        k_out += 1
        if want is not None and not want(k_out - 1):
            return t, None
        pool = pool or FramePool(stats.shape, pool_cap(stats.shape, stats.box))
        if stats.static:
            return t, pool.filled(stats.box, lambda v: np.copyto(v, c16))
        mean = np.multiply(st.s1, np.float32(1.0 / len(buf)), out=st.mean)
        return t, pool.filled(stats.box, lambda v: np.subtract(c16, mean, out=v, dtype=np.float32))

    it = iter(frames)
    for t, img in it:
        push(t, img)
        if len(buf) == n_win:
            break
    if not buf:
        return
    centre = min(half, len(buf) - 1)
    for k in range(centre + 1):
        yield emit(buf[k], times[k])
    for t, img in it:
        pop()
        push(t, img)
        yield emit(buf[half], times[half])
    start = half + 1 if len(buf) == n_win else centre + 1
    for j in range(start, len(buf)):
        yield emit(buf[j], times[j])


def _standardize(frames, roi, *, margin: int, half: int, shrink: float, stats: SurfaceStats, spare=None):
    """The standardised box crops (float32), one per frame, ``half`` frames after it went in; a crop is
    written into one of ``spare`` (a list the consumer hands its used crops back to) when there is one."""
    it = iter(frames)
    n_win = 2 * half + 1
    buf: deque = deque()
    times: deque = deque()
    st = _Sums()
    box = ref = dtype = mag = None
    free_u8: list[np.ndarray] = []  # uint8 crops the window let go, written again by a later frame

    def push(t, img):
        nonlocal box, dtype
        a = np.asarray(img)
        if box is None:
            stats.shape = a.shape
            box = stats.box = _box(a.shape, roi, margin)
            dtype = _window_dtype(box, n_win)
        x0, y0, x1, y1 = box
        c = a[y0:y1, x0:x1]
        c = _copy_into(free_u8, c) if c.dtype == np.uint8 else c.astype(np.float32)
        st.add(c)
        buf.append(_stored(c, dtype))
        times.append(float(t))

    def pop():
        old = buf.popleft()
        st.remove(old)
        times.popleft()
        if old.dtype == np.uint8:
            free_u8.append(old)

    def moments():
        nonlocal ref
        if st.updates >= _RESUM_EVERY:  # running float32 sums drift: recompute them from the window now and then
            st.reset(buf)
        mean, sd = st.moments(len(buf))
        if ref is None:  # the box's typical spread, from the first window
            med = float(np.median(sd))
            stats.static = med < 1e-3
            ref = stats.std_ref = max(med, 1e-3)
            stats.specular_fraction = float(np.mean(sd > 4.0 * ref))
        sd += ref
        return mean, sd

    def emit(c16: np.ndarray, t: float, mom) -> tuple[float, np.ndarray]:
        """The standardised box crop of one frame (float32)."""
        nonlocal mag
        mean, den = mom
        o = spare.pop() if spare else np.empty(c16.shape, np.float32)
        stats.frames += 1
        if stats.static:
            o[:] = c16
            return t, o
        if c16.dtype == np.float16:
            np.subtract(c16, mean, out=o, dtype=np.float32)
        else:
            cv2.subtract(c16, mean, dst=o, dtype=cv2.CV_32F)
        cv2.divide(o, den, dst=o)
        if shrink > 0:  # soft threshold: sign(o) max(|o| - tau, 0) = o - clip(o, -tau, tau)
            tau = float(np.float32(shrink * 1.4826 * np.median(np.abs(o[::4, ::4]))))
            if mag is None:
                mag = np.empty_like(o)
            # older stubs take arrays only (OpenCV takes a scalar as the second operand); newer ones accept it
            cv2.max(o, -tau, dst=mag)  # type: ignore[call-overload, unused-ignore]
            cv2.min(mag, tau, dst=mag)  # type: ignore[call-overload, unused-ignore]
            cv2.subtract(o, mag, dst=o)
        return t, o

    for t, img in it:  # fill the first window
        push(t, img)
        if len(buf) == n_win:
            break
    if not buf:
        return
    mom = moments()
    centre = min(half, len(buf) - 1)
    for k in range(centre + 1):  # the first frames use the first full window
        yield emit(buf[k], times[k], mom)
    for t, img in it:
        pop()
        push(t, img)
        yield emit(buf[half], times[half], moments())
    start = half + 1 if len(buf) == n_win else centre + 1
    for j in range(start, len(buf)):  # the last frames use the last full window
        yield emit(buf[j], times[j], mom if len(buf) < n_win else moments())


_RESUM_EVERY = 256


def _copy_into(free: list[np.ndarray], c: np.ndarray) -> np.ndarray:
    """A copy of ``c``, written into one of ``free`` (arrays of its shape let go) when there is one."""
    if not free:
        return c.copy()
    out = free.pop()
    np.copyto(out, c)
    return out


class _Sums:
    """Running per-pixel sums of I and I² over the window (float32, recomputed every ``_RESUM_EVERY`` updates);
    ``squares=False``: of I only (the recentring needs the mean alone)."""

    def __init__(self, squares=True):
        self.s1 = self.s2 = self.tmp = self.mean = self.sd = None
        self.squares = squares
        self.updates = 0

    def add(self, c: np.ndarray) -> None:
        """Add a crop (uint8, float32 or float16)."""
        if self.s1 is None:
            self.s1, self.mean = np.zeros(c.shape, np.float32), np.zeros(c.shape, np.float32)
            if self.squares:
                self.s2, self.tmp, self.sd = (np.zeros(c.shape, np.float32) for _ in range(3))
        if c.dtype == np.float16:  # OpenCV has no float16 sums
            np.add(self.s1, c, out=self.s1)
            if self.squares:
                np.multiply(c, c, out=self.tmp, dtype=np.float32)
                self.s2 += self.tmp
        else:  # one pass each, where numpy takes three
            cv2.accumulate(c, self.s1)
            if self.squares:
                cv2.accumulateSquare(c, self.s2)
        self.updates += 1

    def remove(self, c16: np.ndarray) -> None:
        """Take a crop out (as it was added). uint8 crops by OpenCV (the same float32 numbers: its square is
        exact, each difference rounded once, in a third of numpy's time for the mixed types)."""
        if c16.dtype == np.uint8:
            cv2.subtract(self.s1, c16, dst=self.s1, dtype=cv2.CV_32F)
            if self.squares:
                cv2.multiply(c16, c16, dst=self.tmp, dtype=cv2.CV_32F)
                self.s2 -= self.tmp
        else:
            np.subtract(self.s1, c16, out=self.s1)
            if self.squares:
                np.multiply(c16, c16, out=self.tmp, dtype=np.float32)
                self.s2 -= self.tmp
        self.updates += 1

    def reset(self, buf) -> None:
        """The sums computed again from the window's crops (running float32 sums drift)."""
        self.s1[:] = 0
        if self.squares:
            self.s2[:] = 0
        for c in buf:
            self.add(c)
        self.updates = 0

    def moments(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(mean, standard deviation) over the window, in two buffers that the next call overwrites."""
        mean, var = self.mean, self.sd
        np.multiply(self.s1, np.float32(1.0 / n), out=mean)
        np.multiply(self.s2, np.float32(1.0 / n), out=var)
        np.multiply(mean, mean, out=self.tmp)
        var -= self.tmp
        cv2.max(var, 0.0, dst=var)  # type: ignore[call-overload, unused-ignore]
        return mean, cv2.sqrt(var, dst=var)  # correctly rounded, as numpy's (both 4x numpy's speed here)
