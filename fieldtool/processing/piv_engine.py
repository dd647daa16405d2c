"""The PIV correlation engine: pass geometry, window spectra, correlation planes, peaks (CPU, scipy.fft).

``piv.analyze`` drives it over a stream of frames (its module docstring says how the whole works); the GPU engine
(``piv_gpu``) and the OpenPIV reference (``piv_openpiv``) reuse its geometry and peak search. Here:

* :class:`PivParams` (the project's ``[piv]`` table) and :func:`_levels`, which checks them against the frame or
  ROI and builds the passes (:class:`_Level`: window side, search side, node spacing, first window; px);
* the window spectra (strided views, one batched real FFT per frame), the correlation planes (inverse FFT of
  ``conj(A) * B``) and the peak search (Gaussian 3-point sub-pixel fit; peak ratio, peak-to-mean, peak value);
* :class:`_Engine`: one pair through every pass (window deformation with ``cv2.remap`` between passes).

Conventions: image axes, +x right, +y down, origin at the centre of the top-left pixel; displacements in px.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from fieldtool.errors import Cancelled, ParameterError
from fieldtool.processing import piv_peaks
from fieldtool.processing import piv_validate as pv

AVERAGING = ("ensemble", "mean", "median")
ENGINES = ("fieldtool", "openpiv")
_WORKERS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


#: glibc serves blocks over its mmap threshold (at most 32 MiB however it adapts) from fresh pages and returns
#: them to the kernel when freed: every frame's window spectra (34 MB at 1080p, 32 px windows) were faulted in
#: again. Raised for this process so they are reused from the heap (1080p pairs, single pass: CPU 0.85 -> 0.71 s
#: for 8 pairs; two passes 2.7 -> 2.1 s); freed memory above ``_TRIM_BYTES`` at the heap's top still goes back
_MMAP_BYTES = 128 << 20
_TRIM_BYTES = 64 << 20


def _tune_allocator() -> None:
    """Raise glibc's mmap and trim thresholds (see ``_MMAP_BYTES``); nothing elsewhere (no glibc)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    mallopt(-3, _MMAP_BYTES)  # M_MMAP_THRESHOLD
    mallopt(-1, _TRIM_BYTES)  # M_TRIM_THRESHOLD


if sys.platform.startswith("linux"):
    _tune_allocator()


def _sfft():
    """scipy.fft, imported on first use: a process that only unpickles a PIV result (the figure process,
    plots/prerender.py) does not pay its import (0.25 s of CPU: scipy.special and SciPy's array-API layer)."""
    import scipy.fft

    return scipy.fft


_POOL: ThreadPoolExecutor | None = None
#: bytes of correlation planes per chunk of nodes (:func:`chunked`): a chunk's planes stay in the core's cache
#: through the product, the inverse FFT and the peak search. 1080p pairs, 32 px windows: 1 chunk 58-87 ms, chunks
#: of 4 MiB 43-46 ms on one thread and 25-31 ms on two (of 2 cores)
_CHUNK_BYTES = 4 << 20


def set_fft_workers(n: int) -> None:
    """Threads of each batched FFT and of the chunked correlation (default: the cores this process may use).
    Batch runs with one process per core set 1, so that N processes do not start N x N threads."""
    global _WORKERS, _POOL
    _WORKERS = max(1, int(n))
    if _POOL is not None:
        _POOL.shutdown(wait=False)
        _POOL = None


def _chunk_nodes(s: int) -> int:
    """Nodes per chunk for planes of side ``s`` (float32)."""
    return max(16, _CHUNK_BYTES // (4 * s * s))


def chunked(n: int, size: int, fn) -> list:
    """``[fn(lo, hi) for each chunk]`` over ``range(n)`` in chunks of ``size``, on ``_WORKERS`` threads (NumPy,
    SciPy's FFT and OpenCV release the GIL) or in the calling thread when there is one chunk or one worker.
    ``fn`` must write only its own rows. Results in chunk order."""
    bounds = [(lo, min(lo + size, n)) for lo in range(0, n, size)] or [(0, 0)]
    if len(bounds) == 1 or _WORKERS == 1:
        return [fn(lo, hi) for lo, hi in bounds]
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(_WORKERS, thread_name_prefix="piv")
    futures = [_POOL.submit(fn, lo, hi) for lo, hi in bounds]
    return [f.result() for f in futures]


_SNR_CAP = 1000.0  # peak ratio reported when the plane has no positive second peak
#: multi-pass: Gaussian smoothing of the predictor between passes (sigma in node spacings), as OpenPIV's windef
#: smooths its own; 0.5 was the best of 0 / 0.5 / 0.6 / 0.8 / 1.2 on benchmarks/piv_vs_openpiv.py (worst RMS 0.068 ->
#: 0.059 px, sparse Rankine vortex) and changes the uniform cases by at most 0.001 px
_PREDICTOR_SMOOTH = 0.5
_SKIP_MASKED = True  # final pass: nodes whose window centre is masked are not correlated (no FFT, no peak)
_DEFORM_INTERP = cv2.INTER_LANCZOS4  # image interpolation of the window deformation (multi-pass)


@dataclass
class PivParams:
    """PIV parameters; keys match the project's ``[piv]`` table."""

    window_px: int = 32  # final interrogation window side (px)
    overlap_px: int = 16  # overlap between windows (px)
    search_px: int | None = None  # search area side in the first pass (px); None = first-pass window
    passes: int = 1  # multi-pass with window deformation; window halves each pass (64 -> 32 with passes=2)
    snr_min: float = 1.3  # peak-to-second-peak minimum
    averaging: str = "ensemble"  # ensemble | mean | median
    median_threshold: float = 2.0  # normalised local median test
    std_threshold: float = 4.0  # global std test (n sigma)
    min_valid_fraction: float = 0.3  # node valid in fewer pairs than this fraction -> invalid in the average
    engine: str = "fieldtool"  # fieldtool | openpiv (OpenPIV extended_search_area_piv / windef, same outputs)
    min_texture: float = (
        0.0  # window rms (frame units) below which a window is featureless: no vector, no ensemble weight
    )
    frame_gap: int = 1  # pairs are frames (i, i + frame_gap) of the stream (processing/planning.py chooses it)
    remove_zero_peak: bool = (
        False  # ensemble, passes > 1: drop a peak at absolute zero where the node moves (piv_peaks)
    )

    @property
    def first_window_px(self) -> int:
        """The first pass' window side (px): ``window_px`` doubled ``passes - 1`` times."""
        return self.window_px * 2 ** (self.passes - 1)


# --------------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class _Level:
    """One pass: window side w, B-window (search) side s >= w, node spacing, first window's top-left pixel."""

    w: int
    s: int
    step: int
    nx: int
    ny: int
    left: int
    top: int

    @property
    def margin(self) -> int:
        return (self.s - self.w) // 2

    @property
    def xc(self) -> np.ndarray:
        return self.left + (self.w - 1) / 2.0 + self.step * np.arange(self.nx)

    @property
    def yc(self) -> np.ndarray:
        return self.top + (self.w - 1) / 2.0 + self.step * np.arange(self.ny)


def _roi_box(shape: tuple[int, int], roi) -> tuple[int, int, int, int]:
    h, w = int(shape[0]), int(shape[1])
    if roi is None:
        return 0, 0, w, h
    try:
        x0, y0, x1, y1 = (int(round(float(c))) for c in roi)
    except (TypeError, ValueError):
        raise ParameterError(f"roi: expected 4 numbers [x0, y0, x1, y1] in pixels, got {roi!r}") from None
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ParameterError(
            f"roi: {roi!r} leaves no usable area inside the {w} x {h} px frame; pick the ROI inside the image"
        )
    return x0, y0, x1, y1


def _levels(shape: tuple[int, int], params: PivParams, roi) -> tuple[list[_Level], tuple[int, int, int, int]]:
    """Validate the parameters against the frame/ROI and build the pass geometry (coarsest first)."""
    p = params
    for key in ("window_px", "overlap_px", "passes"):
        val = getattr(p, key)
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)):
            raise ParameterError(f"piv.{key}: expected a whole number, got {val!r}")
    if p.window_px < 8:
        raise ParameterError(f"piv.window_px: {p.window_px} px is too small; use 8 px or more (16, 32, 64 are usual)")
    if p.overlap_px < 0 or p.overlap_px >= p.window_px:
        raise ParameterError(
            f"piv.overlap_px: {p.overlap_px} px must be at least 0 and smaller than piv.window_px "
            f"({p.window_px} px); half the window ({p.window_px // 2} px) is usual"
        )
    if not 1 <= p.passes <= 4:
        raise ParameterError(f"piv.passes: {p.passes} must be between 1 and 4")
    if p.averaging not in AVERAGING:
        raise ParameterError(f"piv.averaging: {p.averaging!r} is not one of {', '.join(AVERAGING)}")
    if p.engine not in ENGINES:
        raise ParameterError(f"piv.engine: {p.engine!r} is not one of {', '.join(ENGINES)}")
    for key, lo in (("snr_min", 0.0), ("median_threshold", 0.0), ("std_threshold", 0.0)):
        val = getattr(p, key)
        if not isinstance(val, (int, float)) or not np.isfinite(val) or val <= lo:
            raise ParameterError(f"piv.{key}: {val!r} must be a number above {lo:g}")
    if not 0.0 <= p.min_valid_fraction <= 1.0:
        raise ParameterError(f"piv.min_valid_fraction: {p.min_valid_fraction!r} must be between 0 and 1")

    x0, y0, x1, y1 = _roi_box(shape, roi)
    rw, rh = x1 - x0, y1 - y0
    where = "the ROI" if roi is not None else "the image"
    w0 = p.first_window_px
    if w0 > min(rw, rh):
        if p.passes > 1:
            raise ParameterError(
                f"piv.passes: the first pass uses {w0} px windows (piv.window_px {p.window_px} doubled "
                f"{p.passes - 1} times), larger than {where} ({rw} x {rh} px); use fewer passes or a smaller window"
            )
        fit = 2 ** int(np.log2(max(min(rw, rh), 1)))
        raise ParameterError(
            f"piv.window_px: {p.window_px} px is larger than {where} ({rw} x {rh} px); use {fit} or less"
        )
    s0 = w0
    if p.search_px is not None:
        if isinstance(p.search_px, bool) or not isinstance(p.search_px, (int, np.integer)):
            raise ParameterError(f"piv.search_px: expected a whole number or nothing, got {p.search_px!r}")
        if p.search_px < w0:
            raise ParameterError(
                f"piv.search_px: {p.search_px} px is smaller than the first-pass window ({w0} px); "
                f"use {w0} px or more, or leave it empty"
            )
        s0 = int(p.search_px) + (int(p.search_px) - w0) % 2  # (search - window) must be even
    step = p.window_px - p.overlap_px
    levels = []
    for k in range(p.passes):
        f = 2 ** (p.passes - 1 - k)
        w, st = p.window_px * f, step * f
        nx = (rw - w) // st + 1
        ny = (rh - w) // st + 1
        left = x0 + ((rw - w) - (nx - 1) * st) // 2
        top = y0 + ((rh - w) - (ny - 1) * st) // 2
        levels.append(_Level(w=w, s=s0 if k == 0 else w, step=st, nx=nx, ny=ny, left=left, top=top))
    return levels, (x0, y0, x1, y1)


def check_params(shape: tuple[int, int], params: PivParams, roi=None) -> None:
    """Raise ParameterError (naming the ``piv.*`` key) if ``params`` cannot run on a frame of ``shape`` (H, W)."""
    _levels(shape, params, roi)


def grid(shape: tuple[int, int], params: PivParams, roi: tuple[int, int, int, int] | None = None):
    """Node centres of the final pass.

    Parameters
    ----------
    shape : (H, W) of the frame, px.
    params : PivParams.
    roi : (x0, y0, x1, y1) in full-frame pixels, x1/y1 exclusive; None = whole frame.

    Returns
    -------
    x, y : (ny, nx) node centres in full-frame pixel coordinates (window centres; the grid is centred in the ROI).
    """
    lv = _levels(shape, params, roi)[0][-1]
    return np.meshgrid(lv.xc, lv.yc)


# --------------------------------------------------------------------------------------------- correlation core


def _window_view(img: np.ndarray, oy: int, ox: int, lv: _Level, size: int) -> np.ndarray:
    """Strided view (ny, nx, size, size) of the windows of side ``size`` whose top-left corners start at crop pixel
    ``(oy, ox)`` and repeat every ``lv.step`` px (no copy)."""
    view = np.lib.stride_tricks.sliding_window_view(img, (size, size))
    return view[oy : oy + lv.step * (lv.ny - 1) + 1 : lv.step, ox : ox + lv.step * (lv.nx - 1) + 1 : lv.step]


def _window_spectra(
    img: np.ndarray, oy: int, ox: int, lv: _Level, size: int, idx: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Spectra (n, s, s//2+1) of the windows of side ``size`` at crop offset (oy, ox), zero-mean, zero-padded to the
    level's search side ``lv.s`` when ``size < lv.s``, and the factor (n,) that scales each to unit energy.
    ``idx``: flat node indices (row-major) of the only windows to transform (n = len(idx)); None = all.

    The unit-energy scaling is not applied to the spectra: a correlation plane is scaled by the product of its two
    windows' factors only where a value is reported (peak value, ensemble sum), which saves a pass over the spectra.
    With ``size == lv.s`` the mean is removed on the spectrum (DC set to 0) and the energy comes from Parseval. A
    ``size == lv.s > lv.w`` window (search area of frame B) is scaled to the energy of a ``lv.w`` window so its
    correlation values stay comparable to correlation coefficients. A featureless window gets the factor 0.
    """
    view = _window_view(img, oy, ox, lv, size)
    n = lv.ny * lv.nx
    if idx is not None:  # a copy of the chosen windows only
        view = view[idx // lv.nx, idx % lv.nx][:, None]
        n = len(idx)
    return _stack_spectra(view, n, lv, size)


def _shifted_windows(
    img: np.ndarray, oy: int, ox: int, lv: _Level, shift: np.ndarray, idx: np.ndarray | None
) -> np.ndarray:
    """The windows (n, 1, w, w) of side ``lv.w`` at crop offset (oy, ox), each moved by its node's whole-pixel
    ``shift`` (ny * nx, 2: x, y); ``idx`` as in :func:`_window_spectra`."""
    flat = np.arange(lv.ny * lv.nx) if idx is None else idx
    r0 = oy + lv.step * (flat // lv.nx) + shift[flat, 1]
    c0 = ox + lv.step * (flat % lv.nx) + shift[flat, 0]
    a = np.arange(lv.w)
    return img[(r0[:, None] + a)[:, :, None], (c0[:, None] + a)[:, None, :]][:, None]


def _stack_spectra(view: np.ndarray, n: int, lv: _Level, size: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_window_spectra` of windows (n, 1, size, size) or a strided view (ny, nx, size, size)."""
    s = lv.s
    if size == s:
        spec = _sfft().rfft2(view, axes=(2, 3), workers=_WORKERS).reshape(n, s, s // 2 + 1)
        spec[:, 0, 0] = 0.0  # zero mean
        fv = spec.view(np.float32)  # (n, s, 2 * (s // 2 + 1)): re, im interleaved
        # Parseval for the half spectrum: each column stands for two columns of the full spectrum, except column 0
        # and, for an even s, the Nyquist column s/2; sum |X|^2 / s^2 = sum (x - mean)^2
        cols = np.full(fv.shape[2], 2.0 / float(s * s), np.float32)
        cols[:2] = 1.0 / float(s * s)
        if s % 2 == 0:
            cols[-2:] = 1.0 / float(s * s)
        energy = np.einsum("nij,nij->nj", fv, fv) @ cols
        if s != lv.w:
            energy *= (lv.w / s) ** 2
    else:
        win = view.reshape(n, size, size)  # copy
        win -= win.mean(axis=(1, 2), dtype=np.float32)[:, None, None]
        energy = np.einsum("nij,nij->n", win, win)
        spec = _sfft().rfft2(win, s=(s, s), axes=(1, 2), workers=_WORKERS)
    with np.errstate(divide="ignore"):
        scale = np.where(energy > 1e-6, 1.0 / np.sqrt(np.maximum(energy, 1e-12)), 0.0).astype(np.float32)
    return spec, scale


def _irfft2(spec: np.ndarray, s: int, workers: int | None = None) -> np.ndarray:
    """Real planes (n, s, s) of half spectra (n, s, s//2+1), as ``scipy.fft.irfft2``; ``spec`` is overwritten.

    A complex inverse FFT along the columns then a real one along the rows: the same transform, about 1.5x faster
    than ``irfft2`` on many small planes with SciPy's pocketfft.
    """
    nw = _WORKERS if workers is None else workers
    fft = _sfft()
    tmp = fft.ifft(spec, axis=1, workers=nw, overwrite_x=True)
    return fft.irfft(tmp, n=s, axis=2, workers=nw, overwrite_x=True)


def _gauss3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Sub-pixel offset of a peak b between a (at -1) and c (at +1): Gaussian fit, parabolic where not all > 0."""
    pos = (a > 0) & (b > 0) & (c > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        la, lb, lc = (np.log(np.where(pos, z, 1.0)) for z in (a, b, c))
        den_g = 2.0 * la - 4.0 * lb + 2.0 * lc
        den_p = 2.0 * a - 4.0 * b + 2.0 * c
        off = np.where(pos, (la - lc) / den_g, (a - c) / den_p)
    off = np.where(np.isfinite(off), off, 0.0)
    return np.clip(off, -0.5, 0.5)


@dataclass
class _Peaks:
    dx: np.ndarray  # (n,) px, displacement of B relative to A
    dy: np.ndarray
    peak: np.ndarray  # first peak value
    snr: np.ndarray  # peak / second peak
    p2m: np.ndarray  # peak-to-mean ratio: peak / root-mean-square of the (zero-mean) plane
    ok: np.ndarray  # peak found inside the search range (not on its edge) and plane not empty


_NB8 = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def _local_max(plane: np.ndarray) -> np.ndarray:
    """(m, k, k) bool: value >= its 8 neighbours, the plane taken as circular (3 x 3 ``cv2.dilate`` of the
    planes padded circularly by one cell and stacked into one image)."""
    m, k, _ = plane.shape
    pad = np.empty((m, k + 2, k + 2), np.float64 if plane.dtype == np.float64 else np.float32)
    pad[:, 1:-1, 1:-1] = plane
    pad[:, 0, 1:-1], pad[:, -1, 1:-1] = plane[:, -1], plane[:, 0]
    pad[:, :, 0], pad[:, :, -1] = pad[:, :, -2], pad[:, :, 1]
    dil = cv2.dilate(pad.reshape(m * (k + 2), k + 2), np.ones((3, 3), np.uint8)).reshape(m, k + 2, k + 2)
    return plane >= dil[:, 1:-1, 1:-1]


def _find_peaks(corr: np.ndarray, margin: int, scale: np.ndarray | None = None, second: bool = True) -> _Peaks:
    """Peaks of correlation planes (n, s, s) in FFT order (index k <-> displacement k - margin, circular).

    ``second=False`` skips the second-peak search (the SNR is then reported as the cap): for predictor passes,
    which do not judge vectors by their SNR.

    ``scale`` (n,): factor that turns a plane into correlation coefficients (product of its windows' unit-energy
    factors; None = the planes are normalised already). Only the reported peak value depends on it; a plane with
    the factor 0 (featureless window) gives no vector. ``corr`` is left as it was.
    """
    n, s, _ = corr.shape
    rows = np.arange(n)
    flat = corr.reshape(n, s * s)
    rms = np.sqrt(np.einsum("ij,ij->i", flat, flat) / float(s * s))  # the plane has zero mean
    if margin > 0:
        span = 2 * margin + 1
        region = np.ascontiguousarray(corr[:, :span, :span])  # a copy: blanked below
    else:
        span = s
        region = corr
    rflat = region.reshape(n, span * span)
    ky, kx = np.divmod(rflat.argmax(axis=1), span)
    c = corr[rows, ky, kx].astype(np.float64)
    cl, cr = corr[rows, ky, (kx - 1) % s], corr[rows, ky, (kx + 1) % s]
    cu, cd = corr[rows, (ky - 1) % s, kx], corr[rows, (ky + 1) % s, kx]
    if margin > 0:
        ix, iy = kx - margin, ky - margin
        edge = (kx == 0) | (ky == 0) | (kx == span - 1) | (ky == span - 1)
        sx, sy = _gauss3(cl, c, cr), _gauss3(cu, c, cd)
    else:
        ix = np.where(kx < s // 2, kx, kx - s)
        iy = np.where(ky < s // 2, ky, ky - s)
        edge = (ix == -(s // 2)) | (iy == -(s // 2))
        # loss of pairs: at shift k only (s - |k|) / s of a window matches, which pulls the peak towards zero;
        # divide the three points by that weight before the fit (Raffel et al., PIV, 3rd ed., 5.4)
        wx = 1.0 - np.abs(ix[:, None] + np.array([-1, 0, 1])) / s
        wy = 1.0 - np.abs(iy[:, None] + np.array([-1, 0, 1])) / s
        sx = _gauss3(cl / wx[:, 0], c / wx[:, 1], cr / wx[:, 2])
        sy = _gauss3(cu / wy[:, 0], c / wy[:, 1], cd / wy[:, 2])
    # second peak: the highest local maximum (value >= its 8 neighbours, the searched region taken as circular)
    # outside a 5 x 5 neighbourhood of the first. Only local maxima count: elongated particle images (oblique
    # views) give a broad first peak whose shoulder is not a second peak. The highest value outside the
    # neighbourhood is that maximum whenever it passes the local-maximum test; only planes where it fails (it
    # sits on the first peak's shoulder) are searched in full.
    if not second:
        p2 = np.full(n, np.nan)
    else:
        off = np.arange(-2, 3)
        yy = (ky[:, None] + off) % s
        xx = (kx[:, None] + off) % s
        if margin > 0:  # neighbourhood cells outside the searched region are not in it
            yy = np.where(yy < span, yy, ky[:, None])
            xx = np.where(xx < span, xx, kx[:, None])
        blk = (rows[:, None, None], yy[:, :, None], xx[:, None, :])
        saved = region[blk] if region is corr else None
        region[blk] = -np.inf
        j = rflat.argmax(axis=1)
        p2 = rflat[rows, j].astype(np.float64)
        if saved is not None:
            region[blk] = saved
        orig = corr[:, :span, :span]
        cy, cx = np.divmod(j, span)
        found = np.isfinite(p2)
        is_max = found.copy()
        for dy_, dx_ in _NB8:
            is_max &= p2 >= orig[rows, (cy + dy_) % span, (cx + dx_) % span]
        redo = np.flatnonzero(found & ~is_max)
        if redo.size:
            sub = orig[redo]
            cand = _local_max(sub)
            cand[(np.arange(redo.size)[:, None, None], yy[redo][:, :, None], xx[redo][:, None, :])] = False
            p2[redo] = np.where(cand, sub, -np.inf).reshape(redo.size, -1).max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(p2 > 0, c / p2, _SNR_CAP)
        p2m = c / rms
    ok = (c > 0) & (rms > 0) & ~edge
    if scale is not None:
        ok &= scale > 0
        c = c * scale
    snr = np.where(ok, np.minimum(snr, _SNR_CAP), np.nan)
    p2m = np.where(ok, p2m, np.nan)
    return _Peaks(dx=ix + sx, dy=iy + sy, peak=c, snr=snr, p2m=p2m, ok=ok)


def _concat_peaks(parts: list) -> _Peaks:
    """The peaks of consecutive chunks of nodes as one :class:`_Peaks`."""
    if len(parts) == 1:
        return parts[0]
    return _Peaks(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in _Peaks.__dataclass_fields__})


def _scatter_peaks(pk: _Peaks, idx: np.ndarray, n: int) -> _Peaks:
    """Peaks of the nodes ``idx`` spread onto all ``n`` nodes; the others have no vector (NaN, not ok)."""
    out = {}
    for name in ("dx", "dy", "peak", "snr", "p2m"):
        arr = np.full(n, np.nan)
        arr[idx] = getattr(pk, name)
        out[name] = arr
    ok = np.zeros(n, bool)
    ok[idx] = pk.ok
    return _Peaks(ok=ok, **out)


def _guess_at(
    lv: _Level, xc: np.ndarray, yc: np.ndarray, dx: np.ndarray, dy: np.ndarray, whole: bool = True
) -> np.ndarray:
    """Offsets (ny * nx, 2: x, y) of the level's nodes from a first guess (dx, dy) (px per pair) on the regular
    grid of centres xc (nx,), yc (ny,): bilinear, edges replicated; NaN guesses count as 0. ``whole``: rounded
    to whole pixels (int64), else float32."""
    gx = ((lv.xc - xc[0]) / max(float(xc[1] - xc[0]), 1e-9) if len(xc) > 1 else 0 * lv.xc).astype(np.float32)
    gy = ((lv.yc - yc[0]) / max(float(yc[1] - yc[0]), 1e-9) if len(yc) > 1 else 0 * lv.yc).astype(np.float32)
    fx, fy = np.meshgrid(gx, gy)
    field = np.nan_to_num(np.dstack([dx, dy]).astype(np.float32))
    out = cv2.remap(field, fx, fy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)
    return np.rint(out).astype(np.int64) if whole else out


def near_nodes(lv: _Level, segments, reach_px: float) -> np.ndarray:
    """Bool (ny, nx): the nodes of level ``lv`` whose centre is within ``reach_px`` px of one of ``segments``
    (each a (2, 2) array of two image points, full-frame px)."""
    X, Y = np.meshgrid(lv.xc, lv.yc)
    P = np.stack([X.ravel(), Y.ravel()], axis=1)
    best = np.full(len(P), np.inf)
    for seg in segments:
        a, b = np.asarray(seg, float).reshape(2, 2)
        ab = b - a
        t = np.clip((P - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.hypot(*(P - a - t[:, None] * ab).T))
    return (best <= float(reach_px)).reshape(lv.ny, lv.nx)


# --------------------------------------------------------------------------------------------- the engine


@dataclass
class _Frame:
    """What the engine keeps of one frame: its crop (multi-pass only) and window spectra."""

    img: np.ndarray | None
    spec_a: list  # per level: spectra of the zero-mean A windows (padded to the level's search side)
    spec_b0: np.ndarray | None  # first level: spectra of the B windows (search side); None: not a second frame
    scale_a: list | None = None  # per level: unit-energy factors of the A windows (None: spectra normalised)
    scale_b0: np.ndarray | None = None  # first level: unit-energy factors of the B windows


class _Engine:
    """Correlation of consecutive frames on fixed pass geometry (CPU, scipy.fft)."""

    def __init__(
        self, shape, params: PivParams, levels: list[_Level], box, mask: np.ndarray | None, near=None, guess=None
    ):
        """``near``: per level, bool (ny, nx) of the nodes near the section (:func:`near_nodes`), or None."""
        self.p = params
        self.levels = levels
        self.h, self.w = shape
        x0, y0, x1, y1 = box
        # first pass' whole-pixel window offsets (n0, 2: x, y) from the first guess, or None
        self.shift0 = None if guess is None else _guess_at(levels[0], *guess)
        m = levels[0].margin + (0 if self.shift0 is None else int(np.abs(self.shift0).max()))
        self.cx0, self.cy0 = x0 - m, y0 - m  # crop origin in full-frame px (may be negative: padded)
        self.cw, self.ch = (x1 - x0) + 2 * m, (y1 - y0) + 2 * m
        self.box = box
        self.mask_crop = None if mask is None else self._crop(mask.astype(np.uint8), 0) > 0
        if self.mask_crop is not None and not self.mask_crop.any():
            self.mask_crop = None
        self._maps: dict = {}
        self._bufs: dict = {}
        self._strips: dict = {}  # level -> the deformed crop's rectangles its active windows read (_deform_strips)
        # per pass, the flat indices (row-major) of the only nodes correlated (None = all): the final pass of a
        # multi-pass run skips the nodes whose window centre is masked (earlier passes keep them: they build the
        # predictor of the others); with ``near`` every pass skips the nodes beyond its distance of the section
        keep = list(near) if near is not None else [None] * len(levels)
        fin = levels[-1]
        if _SKIP_MASKED and mask is not None and len(levels) > 1:
            X, Y = np.meshgrid(fin.xc, fin.yc)
            node_mask = mask[np.rint(Y).astype(int).clip(0, self.h - 1), np.rint(X).astype(int).clip(0, self.w - 1)]
            if node_mask.any():
                keep[-1] = ~node_mask if keep[-1] is None else keep[-1] & ~node_mask
        self.act = [None if kp is None or kp.all() else np.flatnonzero(kp.ravel()) for kp in keep]

    def _crop(self, img: np.ndarray, fill: float) -> np.ndarray:
        x0, y0 = self.cx0, self.cy0
        xa, ya = max(x0, 0), max(y0, 0)
        xb, yb = min(x0 + self.cw, self.w), min(y0 + self.ch, self.h)
        sub = img[ya:yb, xa:xb]
        if (xa, ya, xb, yb) == (x0, y0, x0 + self.cw, y0 + self.ch):
            return sub
        return cv2.copyMakeBorder(
            np.ascontiguousarray(sub),
            ya - y0,
            y0 + self.ch - yb,
            xa - x0,
            x0 + self.cw - xb,
            cv2.BORDER_CONSTANT,
            value=fill,
        )

    def _offsets(self, lv: _Level) -> tuple[int, int]:
        return lv.top - self.cy0, lv.left - self.cx0

    def _masked_crop(self, frame: np.ndarray) -> np.ndarray:
        """The frame's crop (float32) with masked pixels set to the ROI's mean intensity."""
        f = frame if frame.dtype == np.float32 else frame.astype(np.float32)
        x0, y0, x1, y1 = self.box
        fill = float(f[y0:y1, x0:x1].mean())
        img = self._crop(f, fill)
        if self.mask_crop is not None:
            img = img.copy()
            img[self.mask_crop] = fill
        return img

    def prepare(self, frame: np.ndarray, as_a: bool = True, as_b: bool = True) -> _Frame:
        """Crop, fill the mask with the frame mean, and compute the window spectra of all levels.

        ``as_a=False``: the frame is only the second frame of a pair (``analyze(select=...)``): the A-window
        spectra, which only a first frame needs, are not computed (but the first level's when it is also the
        search area's, ``search_px`` unset). ``as_b=False``: the frame is only a first frame: the first level's
        search-area spectra (``search_px`` set) are not computed."""
        img = self._masked_crop(frame)
        lv0 = self.levels[0]
        same = lv0.s == lv0.w
        spec_a, scale_a = [], []
        spec_b0: np.ndarray | None
        scale_b0: np.ndarray | None
        for k, lv in enumerate(self.levels if as_a else self.levels[: int(same and self.shift0 is None)]):
            oy, ox = self._offsets(lv)
            sp, sc = _window_spectra(img, oy, ox, lv, lv.w, self.act[k])
            spec_a.append(sp)
            scale_a.append(sc)
        if self.shift0 is not None:  # the B windows where the first guess moves them
            if as_b:
                oy, ox = self._offsets(lv0)
                view = _shifted_windows(img, oy, ox, lv0, self.shift0, self.act[0])
                spec_b0, scale_b0 = _stack_spectra(view, len(view), lv0, lv0.w)
            else:
                spec_b0 = scale_b0 = None
        elif same:
            spec_b0, scale_b0 = spec_a[0], scale_a[0]
        elif not as_b:
            spec_b0 = scale_b0 = None
        else:
            oy, ox = self._offsets(lv0)
            spec_b0, scale_b0 = _window_spectra(img, oy - lv0.margin, ox - lv0.margin, lv0, lv0.s, self.act[0])
        return _Frame(
            img=img if len(self.levels) > 1 else None,
            spec_a=spec_a,
            spec_b0=spec_b0,
            scale_a=scale_a,
            scale_b0=scale_b0,
        )

    def _deform(self, k: int, img: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """Frame B's crop deformed by the level k-1 displacement field (du, dv): the region covered by level k's
        windows, each pixel sampled at its position + the displacement (``cv2.remap``, ``_DEFORM_INTERP``).

        The field is interpolated to every pixel bicubically (edges replicated) with one ``cv2.resize`` by the
        node spacing: it maps output pixel j to input node (j + 0.5) / step - 0.5, which is the region's pixel
        i = j - d for a whole number d because the window side and the spacing of level k-1 are both even.
        """
        prev, lv = self.levels[k - 1], self.levels[k]
        oy, ox = self._offsets(lv)
        hh, ww = lv.step * (lv.ny - 1) + lv.w, lv.step * (lv.nx - 1) + lv.w
        st = prev.step
        dx = ox + self.cx0 - prev.left + (st - prev.w) // 2
        dy = oy + self.cy0 - prev.top + (st - prev.w) // 2
        reach = max(-dx, -dy, dx + ww - prev.nx * st, dy + hh - prev.ny * st)
        pad = 1 + max(0, -(-reach // st))  # nodes of replicated border so that the region is inside the resize
        field2 = cv2.copyMakeBorder(np.dstack([du, dv]).astype(np.float32), pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        big = cv2.resize(field2, (field2.shape[1] * st, field2.shape[0] * st), interpolation=cv2.INTER_CUBIC)
        dense = big[dy + pad * st : dy + pad * st + hh, dx + pad * st : dx + pad * st + ww]
        if k not in self._maps:
            self._maps[k] = np.meshgrid(
                np.arange(ox, ox + ww, dtype=np.float32), np.arange(oy, oy + hh, dtype=np.float32)
            )
        px, py = self._maps[k]
        strips = self._deform_strips(k)
        if strips is None:
            mx, my = px + dense[..., 0], py + dense[..., 1]
            return cv2.remap(img, mx, my, _DEFORM_INTERP, borderMode=cv2.BORDER_REPLICATE)
        # only what level k's active windows read (the nodes near the sections): each output pixel of a remap is
        # its own interpolation at its map position, so these pixels are those of the whole remap; the rest of
        # the crop is never read (its windows are not correlated) and stays 0
        out = self._bufs.get(("deform", k))
        if out is None:
            out = self._bufs[("deform", k)] = np.zeros((hh, ww), np.float32)
        for r0, r1, c0, c1 in strips:
            d = dense[r0:r1, c0:c1]
            out[r0:r1, c0:c1] = cv2.remap(
                img,
                px[r0:r1, c0:c1] + d[..., 0],
                py[r0:r1, c0:c1] + d[..., 1],
                _DEFORM_INTERP,
                borderMode=cv2.BORDER_REPLICATE,
            )
        return out

    def _deform_strips(self, k: int) -> list[tuple[int, int, int, int]] | None:
        """The rectangles (row0, row1, col0, col1 px of level k's crop) that its active windows cover: runs of
        rows whose active windows span the same columns; None when every window is active. Fixed per engine."""
        if k in self._strips:
            return self._strips[k]
        act, lv = self.act[k], self.levels[k]
        strips = None
        if act is not None:
            hh = lv.step * (lv.ny - 1) + lv.w
            lo, hi = np.full(hh, np.iinfo(np.int64).max), np.full(hh, -1)
            rows, cols = act // lv.nx, act % lv.nx
            for j in np.unique(rows):
                c = cols[rows == j]
                r = slice(int(j) * lv.step, int(j) * lv.step + lv.w)
                lo[r] = np.minimum(lo[r], int(c.min()) * lv.step)
                hi[r] = np.maximum(hi[r], int(c.max()) * lv.step + lv.w)
            strips, r0 = [], 0
            while r0 < hh:
                r1 = r0 + 1
                while r1 < hh and lo[r1] == lo[r0] and hi[r1] == hi[r0]:
                    r1 += 1
                if hi[r0] >= 0:
                    strips.append((r0, r1, int(lo[r0]), int(hi[r0])))
                r0 = r1
        self._strips[k] = strips
        return strips

    def _node_predictor(self, k: int, du: np.ndarray, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate a level k-1 field (ny, nx) at the node centres of level k (bicubic, edges replicated)."""
        prev, lv = self.levels[k - 1], self.levels[k]
        gx = ((lv.xc - prev.xc[0]) / prev.step).astype(np.float32)
        gy = ((lv.yc - prev.yc[0]) / prev.step).astype(np.float32)
        fx, fy = np.meshgrid(gx, gy)
        field2 = np.dstack([du, dv]).astype(np.float32)
        out = cv2.remap(field2, fx, fy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return out[..., 0].astype(np.float64), out[..., 1].astype(np.float64)

    #: correlate(peaks=False) is supported: the final level's cross-spectrum goes to the ensemble without peaks
    spectrum_only = True

    def correlate(self, a: _Frame, b: _Frame, cancel=None, ensemble=None, peaks: bool = True):
        """Correlate frame a with b through all passes.

        Returns (dx, dy, peaks) of the final level: dx/dy (ny, nx) the total displacement (px) per node (predictor
        + residual). ``ensemble(cross, pred_dx, pred_dy, peaks, scale)`` is called with the final level's
        cross-spectrum (n, s, s//2+1, not normalised: ``scale`` holds the unit-energy factors) and the
        final-level predictor (px; None for a single pass); the callee may modify ``cross``. With
        ``peaks=False`` (needs ``ensemble``) the final level's inverse FFT and peak search are skipped: the
        ensemble gets ``peaks=None`` and (None, None, None) is returned.
        """
        pred_x: np.ndarray | None = None
        pred_y: np.ndarray | None = None
        du: np.ndarray | None = None  # the previous level's field (px), the predictor of the next
        dv: np.ndarray | None = None
        last = len(self.levels) - 1
        for k, lv in enumerate(self.levels):
            if k == 0:
                spec_b, scale_b = b.spec_b0, b.scale_b0
                if self.shift0 is not None:  # the B windows were moved by it: the peak is the residual
                    pred_x = self.shift0[:, 0].reshape(lv.ny, lv.nx).astype(np.float64)
                    pred_y = self.shift0[:, 1].reshape(lv.ny, lv.nx).astype(np.float64)
            else:
                if cancel is not None and cancel():
                    raise Cancelled("PIV cancelled by the user")
                assert b.img is not None and du is not None and dv is not None  # a later pass: set by the one before
                bdef = self._deform(k, b.img, du, dv)
                pred_x, pred_y = self._node_predictor(k, du, dv)
                spec_b, scale_b = _window_spectra(bdef, 0, 0, lv, lv.w, self.act[k])
            assert (
                a.scale_a is not None and spec_b is not None and scale_b is not None
            )  # this engine's frames have them
            scale = a.scale_a[k] * scale_b
            if self.p.min_texture > 0:  # texture gate (processing/surface.py): too little texture -> featureless
                smax = 1.0 / (self.p.min_texture * lv.w)
                scale = np.where((a.scale_a[k] <= smax) & (scale_b <= smax), scale, np.float32(0.0))
            act = self.act[k]
            full = scale_full = None
            if (
                act is not None and ensemble is not None and k == last
            ):  # the ensemble sums every node: masked ones stay 0
                full = self._buffer(("full", k), np.empty((lv.ny * lv.nx,) + a.spec_a[k].shape[1:], np.complex64))
                full[:] = 0
                scale_full = np.zeros(lv.ny * lv.nx, np.float32)
                scale_full[act] = scale
            with_peaks = k < last or peaks
            # the ensemble needs the cross-spectrum after the peaks: each chunk transforms a copy
            keep = k == last and ensemble is not None and act is None
            blank0 = k == 0 and last > 0 and self.p.remove_zero_peak and self.p.frame_gap > 1 and self.shift0 is None
            cross = self._buffer(("cross", k), a.spec_a[k])
            pk = self._cross_and_peaks(
                a.spec_a[k],
                spec_b,
                cross,
                scale,
                lv,
                act,
                full,
                with_peaks,
                keep,
                blank0,
                second=k == last,
            )
            if not with_peaks:
                if full is not None:
                    cross, scale = full, scale_full
                ensemble(cross, pred_x, pred_y, None, scale)
                return None, None, None
            assert pk is not None
            if act is not None:
                pk = _scatter_peaks(pk, act, lv.ny * lv.nx)
                if full is not None:
                    cross, scale, keep = full, scale_full, True
            dx, dy = pk.dx.reshape(lv.ny, lv.nx), pk.dy.reshape(lv.ny, lv.nx)
            if pred_x is not None:
                dx = dx + pred_x
                dy = dy + pred_y
            if k == last:
                if keep:
                    ensemble(cross, pred_x, pred_y, pk, scale)
                return dx, dy, pk
            # predictor for the next pass: validated and filled
            good = pk.ok.reshape(lv.ny, lv.nx) & (pk.snr.reshape(lv.ny, lv.nx) >= 1.0)
            gu, gv = np.where(good, dx, np.nan), np.where(good, dy, np.nan)
            ok = pv.normalized_median_test(gu, gv, self.p.median_threshold)
            du, dv = pv.fill_all(np.where(ok, gu, np.nan), np.where(ok, gv, np.nan))
            if _PREDICTOR_SMOOTH > 0:
                du = cv2.GaussianBlur(du.astype(np.float32), (0, 0), _PREDICTOR_SMOOTH, borderType=cv2.BORDER_REPLICATE)
                dv = cv2.GaussianBlur(dv.astype(np.float32), (0, 0), _PREDICTOR_SMOOTH, borderType=cv2.BORDER_REPLICATE)
        raise AssertionError("unreachable")

    def _cross_and_peaks(
        self,
        spec_a,
        spec_b,
        cross,
        scale,
        lv: _Level,
        act,
        full,
        with_peaks: bool,
        keep: bool,
        blank0: bool,
        second: bool,
    ) -> _Peaks | None:
        """``cross`` = conj(A) * B, and (``with_peaks``) the peaks of its correlation planes, in chunks of nodes
        on the engine's threads (:func:`chunked`). ``full`` (or None): the cross-spectra also go to its rows ``act``.
        ``keep``: ``cross`` must survive the inverse FFT (a chunk transforms a copy); else it is overwritten.
        ``blank0``: the block around zero displacement is blanked on every plane (piv_peaks' module doc)."""

        def one(lo: int, hi: int) -> _Peaks | None:
            c = cross[lo:hi]
            np.conjugate(spec_a[lo:hi], out=c)
            c *= spec_b[lo:hi]
            if full is not None:
                full[act[lo:hi]] = c
            if not with_peaks:
                return None
            corr = _irfft2(c.copy() if keep else c, lv.s, workers=1)
            if blank0:
                zeros = np.zeros(len(corr))
                piv_peaks.blank_zero(corr, lv.margin, zeros, zeros, min_shift=0.0, fill="zero")
            return _find_peaks(corr, lv.margin, scale[lo:hi], second=second)

        parts = chunked(len(cross), _chunk_nodes(lv.s), one)
        return _concat_peaks(parts) if with_peaks else None

    def _buffer(self, key, like: np.ndarray) -> np.ndarray:
        """A work array shaped like ``like``, reused from pair to pair (fresh large arrays cost page faults)."""
        buf = self._bufs.get(key)
        if buf is None or buf.shape != like.shape or buf.dtype != like.dtype:
            buf = self._bufs[key] = np.empty_like(like)
        return buf

    def ensemble_peaks(self, acc: np.ndarray) -> _Peaks:
        """Peaks of the ensemble correlation from the summed (weighted, normalised) cross-spectra of the final pass."""
        lv = self.levels[-1]
        return _find_peaks(_irfft2(acc, lv.s), lv.margin)

    def ensemble_planes(self, acc: np.ndarray) -> np.ndarray:
        """The ensemble correlation planes (n, s, s) of the summed cross-spectra (``acc`` is overwritten)."""
        return _irfft2(acc, self.levels[-1].s)
