"""PIV correlation engine: frame pairs -> per-pair and time-averaged vector fields with quality.

Thesis 2.2.4 (FFT cross-correlation, multi-pass, sub-pixel, validation), 6.2 and 9.2.8.

How it works
------------
* Every frame is cut into interrogation windows with a strided view (no copy of the frame) and all windows go
  through one batched real FFT (``scipy.fft.rfft2``, float32, ``_WORKERS`` threads). The mean is removed on the
  spectrum (DC = 0) and each window's energy comes from Parseval; the unit-energy factor is kept beside the
  spectrum and applied only where a value is reported (peak value, ensemble sum). A frame's window spectra are
  computed once and serve the pair before it (as frame B) and the pair after it (as frame A).
* Correlation plane of a pair = inverse FFT of ``conj(A) * B`` (a column FFT then a row real FFT, into reused
  buffers); the displacement is the highest peak, refined by a Gaussian 3-point fit (parabolic where a value is
  not positive). Quality per vector: peak-to-second-peak ratio, the second peak being the highest local maximum
  (>= its 8 neighbours) outside a 5 x 5 neighbourhood of the first (found as the highest value there, checked
  against its neighbours; a full local-maximum search only on the planes where that value sits on the first
  peak's shoulder), peak-to-mean ratio and the peak value (a correlation coefficient, 1 = perfect match). The
  planes have zero mean (the windows do), so the peak-to-mean ratio is taken on the plane's mean energy:
  peak / root-mean-square.
* ``search_px`` larger than the first window: the A window is zero-padded inside a B window of the search size, so
  displacements up to (search - window) / 2 are found without wrap-around.
* ``first_guess`` (flow too fast for the first window, measured by ``planning.first_look``): the first pass'
  B window of every node is taken where that node's first guess (rounded to whole pixels) moves it, and the
  peak is the residual (window offset); the search area then stays the window.
* ``passes > 1``: the first pass uses windows ``window_px * 2**(passes-1)``; each later pass deforms the second frame
  with ``cv2.remap`` (Lanczos, 8 x 8; bicubic is 4x faster but biased by up to 0.02 px with 4 px particles) by the
  previous pass' validated field, interpolated bicubically to every pixel (one ``cv2.resize`` by the node
  spacing), correlates the smaller windows and adds the residual to the predictor. The first frame's window
  spectra are not deformed, so they are still computed once per frame.
* Masked nodes (window centre in ``mask``) of the final pass of a multi-pass run are not correlated: their
  windows get no spectrum, inverse FFT or peak search (``_SKIP_MASKED``); they have no vector and add nothing to
  the ensemble. Earlier passes keep every node, because they build the predictor of the unmasked ones.
* ``near`` (the fast path's band around the section): in every pass only the nodes within that pass' distance of
  the section segments are correlated, the same way; the final pass' others are treated as masked (no vector,
  never replaced, ``valid_fraction`` NaN), an earlier pass' others are filled from their neighbours.
* Averaging: ``ensemble`` sums the cross-spectra of all pairs per node, weighted by their signal-to-noise
  (weight = clip(peak ratio - 1, 0, 10)), and takes one peak per node at the end (one inverse FFT for the clip);
  ``mean``/``median`` average the validated per-pair vectors.
* Ensemble sample: the ensemble needs no per-pair vectors, so only a sample of ``ENSEMBLE_PAIRS`` (30) to 59
  evenly spaced pairs gets the final pass' inverse FFT, peaks and validation (all pairs of a clip of fewer than
  60 pairs); they give the per-pair fields of the result (``u_pairs``, ``v_pairs``, ``t_pairs``, ``dt_s``,
  ``pair_index``; ``snr``, ``peak2mean``, ``peak``, ``valid_fraction`` are over these pairs; ``on_pair`` is
  called for them) and the SNR weights. The other pairs' cross-spectra are added with each node's mean weight
  over the sampled pairs so far, with no inverse FFT. ``n_pairs`` counts every pair. The stride is
  pairs // 30 when ``frames`` has a length, else it starts at 1 and doubles (every other kept pair dropped)
  each time 60 pairs are kept, which gives vectors to more pairs on the way. Earlier passes of a multi-pass
  run still correlate every pair (they give that pair's predictor).
* Frames are consumed as a stream: only the previous frame's spectra, the reused work buffers and one
  accumulator are held, plus the per-pair fields the result has to return (2 x 4 bytes per node and pair kept;
  in ensemble mode at most 59 pairs whatever the clip length).

Conventions: image axes, +x right, +y down, origin at the centre of the top-left pixel; u, v in px/s from the
frame timestamps. A node's position is the centre of its final interrogation window.
"""

from __future__ import annotations

import os
import warnings
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterable

import cv2
import numpy as np
import scipy.fft

from fieldtool.errors import Cancelled, InputFileError, ParameterError
from fieldtool.processing import piv_validate as pv

#: bumped when the engine gives other vectors for the same inputs (a saved field of another revision is recomputed)
REVISION = 2
AVERAGING = ("ensemble", "mean", "median")
ENGINES = ("fieldtool", "openpiv")
_WORKERS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def set_fft_workers(n: int) -> None:
    """Threads of each batched FFT (default: the cores this process may use). Batch runs with one
    process per core set 1, so that N processes do not start N x N threads."""
    global _WORKERS
    _WORKERS = max(1, int(n))

_SNR_CAP = 1000.0  # peak ratio reported when the plane has no positive second peak
#: averaging = ensemble: per-pair vectors are computed and kept for every k-th pair only, so that between
#: ENSEMBLE_PAIRS and 2 * ENSEMBLE_PAIRS - 1 evenly spaced pairs are kept (all pairs of a clip of fewer than
#: 2 * ENSEMBLE_PAIRS). k = pairs // ENSEMBLE_PAIRS when ``frames`` has a length; for a stream of unknown length
#: k starts at 1 and doubles (every other kept pair dropped) each time 2 * ENSEMBLE_PAIRS pairs are kept.
ENSEMBLE_PAIRS = 30
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
    min_texture: float = 0.0  # window rms (frame units) below which a window is featureless: no vector, no ensemble weight
    frame_gap: int = 1  # pairs are frames (i, i + frame_gap) of the stream (processing/planning.py chooses it)
    remove_zero_peak: bool = False  # ensemble, passes > 1: drop a peak at absolute zero where the node moves (piv_peaks)


@dataclass
class PivResult:
    """Time-averaged and per-pair vector fields on the node grid (image axes, px/s)."""

    x: np.ndarray  # (ny, nx) node centres, px
    y: np.ndarray
    u: np.ndarray  # (ny, nx) time-averaged velocity, px/s; NaN where invalid
    v: np.ndarray
    valid: np.ndarray  # (ny, nx) bool (measured or replaced from valid neighbours)
    valid_fraction: np.ndarray  # (ny, nx) fraction of pairs in which the node was valid
    u_pairs: np.ndarray  # (n_pairs, ny, nx) px/s, NaN = invalid; ensemble: the sampled pairs (module docstring)
    v_pairs: np.ndarray
    t_pairs: np.ndarray  # (n_pairs,) mid-times, s
    snr: np.ndarray  # (ny, nx) median peak-to-second-peak ratio over the pairs
    params: PivParams
    peak2mean: np.ndarray | None = None  # (ny, nx) median peak-to-mean ratio over the pairs
    peak: np.ndarray | None = None  # (ny, nx) median correlation peak value (correlation coefficient)
    replaced: np.ndarray | None = None  # (ny, nx) bool, average filled in from valid neighbours
    ensemble_snr: np.ndarray | None = None  # (ny, nx) peak ratio of the ensemble plane (averaging = ensemble)
    dt_s: np.ndarray | None = None  # (n_pairs,) time between the frames of each pair, s
    pair_index: np.ndarray | None = None  # (n_pairs,) index of each of these pairs in the clip (0 = frames 0-1)
    n_pairs: int | None = None  # pairs correlated in the clip (ensemble: more than the per-pair fields hold)
    zero_peak_removed: np.ndarray | None = None  # (ny, nx) bool, ensemble plane's zero-displacement block blanked
    first_guess: np.ndarray | None = None  # (ny, nx, 2) px per pair: the first pass' window offset (first_guess=)
    carry: object | None = None  # analyze(select=...): state that a later call continues (``carry=``); not saved


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
    w0 = p.window_px * 2 ** (p.passes - 1)
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


def _window_spectra(img: np.ndarray, oy: int, ox: int, lv: _Level, size: int,
                    idx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
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


def _shifted_windows(img: np.ndarray, oy: int, ox: int, lv: _Level, shift: np.ndarray,
                     idx: np.ndarray | None) -> np.ndarray:
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
        spec = scipy.fft.rfft2(view, axes=(2, 3), workers=_WORKERS).reshape(n, s, s // 2 + 1)
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
        spec = scipy.fft.rfft2(win, s=(s, s), axes=(1, 2), workers=_WORKERS)
    with np.errstate(divide="ignore"):
        scale = np.where(energy > 1e-6, 1.0 / np.sqrt(np.maximum(energy, 1e-12)), 0.0).astype(np.float32)
    return spec, scale


def _irfft2(spec: np.ndarray, s: int) -> np.ndarray:
    """Real planes (n, s, s) of half spectra (n, s, s//2+1), as ``scipy.fft.irfft2``; ``spec`` is overwritten.

    A complex inverse FFT along the columns then a real one along the rows: the same transform, about 1.5x faster
    than ``irfft2`` on many small planes with SciPy's pocketfft.
    """
    tmp = scipy.fft.ifft(spec, axis=1, workers=_WORKERS, overwrite_x=True)
    return scipy.fft.irfft(tmp, n=s, axis=2, workers=_WORKERS, overwrite_x=True)


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


def _guess_at(lv: _Level, xc: np.ndarray, yc: np.ndarray, dx: np.ndarray, dy: np.ndarray,
              whole: bool = True) -> np.ndarray:
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
    spec_b0: np.ndarray  # first level: spectra of the B windows (search side)
    scale_a: list | None = None  # per level: unit-energy factors of the A windows (None: spectra normalised)
    scale_b0: np.ndarray | None = None  # first level: unit-energy factors of the B windows


class _Engine:
    """Correlation of consecutive frames on fixed pass geometry (CPU, scipy.fft)."""

    def __init__(self, shape, params: PivParams, levels: list[_Level], box, mask: np.ndarray | None, near=None,
                 guess=None):
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
        if mask is not None and not self.mask_crop.any():
            self.mask_crop = None
        self._maps: dict = {}
        self._bufs: dict = {}
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
            np.ascontiguousarray(sub), ya - y0, y0 + self.ch - yb, xa - x0, x0 + self.cw - xb,
            cv2.BORDER_CONSTANT, value=fill,
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
        return _Frame(img=img if len(self.levels) > 1 else None, spec_a=spec_a, spec_b0=spec_b0, scale_a=scale_a,
                      scale_b0=scale_b0)

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
            self._maps[k] = np.meshgrid(np.arange(ox, ox + ww, dtype=np.float32),
                                        np.arange(oy, oy + hh, dtype=np.float32))
        px, py = self._maps[k]
        return cv2.remap(img, px + dense[..., 0], py + dense[..., 1], _DEFORM_INTERP, borderMode=cv2.BORDER_REPLICATE)

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
        pred_x = pred_y = None
        du = dv = None  # the previous level's field (px), the predictor of the next
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
                bdef = self._deform(k, b.img, du, dv)
                pred_x, pred_y = self._node_predictor(k, du, dv)
                spec_b, scale_b = _window_spectra(bdef, 0, 0, lv, lv.w, self.act[k])
            cross = self._buffer(("cross", k), a.spec_a[k])
            np.conjugate(a.spec_a[k], out=cross)
            cross *= spec_b
            scale = a.scale_a[k] * scale_b
            if self.p.min_texture > 0:  # texture gate (processing/surface.py): too little texture -> featureless
                smax = 1.0 / (self.p.min_texture * lv.w)
                scale = np.where((a.scale_a[k] <= smax) & (scale_b <= smax), scale, np.float32(0.0))
            act = self.act[k]
            if act is not None and ensemble is not None and k == last:  # the ensemble sums every node: masked ones stay 0
                full = self._buffer(("full", k), np.empty((lv.ny * lv.nx,) + cross.shape[1:], cross.dtype))
                full[:] = 0
                full[act] = cross
                scale_full = np.zeros(lv.ny * lv.nx, np.float32)
                scale_full[act] = scale
            if k == last and not peaks:
                if act is not None:
                    cross, scale = full, scale_full
                ensemble(cross, pred_x, pred_y, None, scale)
                return None, None, None
            keep = k == last and ensemble is not None and act is None
            if keep:  # the ensemble needs the cross-spectrum after the peaks: transform a copy
                work = self._buffer(("work", k), cross)
                np.copyto(work, cross)
            corr = _irfft2(work if keep else cross, lv.s)
            if k == 0 and last > 0 and self.p.remove_zero_peak and self.p.frame_gap > 1 and self.shift0 is None:
                from fieldtool.processing import piv_peaks  # no predictor yet: zero is not the flow (module doc)

                zeros = np.zeros(len(corr))
                piv_peaks.blank_zero(corr, lv.margin, zeros, zeros, min_shift=0.0, fill="zero")
            pk = _find_peaks(corr, lv.margin, scale, second=k == last)
            if act is not None:
                pk = _scatter_peaks(pk, act, lv.ny * lv.nx)
                if ensemble is not None and k == last:
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


# --------------------------------------------------------------------------------------------- analyze


def _check_frame(i: int, img, shape) -> np.ndarray:
    arr = np.asarray(img)
    if arr.ndim != 2:
        raise InputFileError(
            f"frames: frame {i} has shape {arr.shape}; PIV needs single-channel (gray) frames — convert them first"
        )
    if shape is not None and arr.shape != shape:
        raise InputFileError(f"frames: frame {i} is {arr.shape[1]} x {arr.shape[0]} px, the first was "
                             f"{shape[1]} x {shape[0]} px; all frames of a clip must have the same size")
    return arr


def _pair_validity(dx, dy, pk_ok, snr, dt, params, node_mask, max_speed):
    """Per-pair validation of displacements (px): peak found, SNR, mask, speed, global std, local median."""
    ok = pk_ok & (np.isnan(snr) | (snr >= params.snr_min)) & ~node_mask  # NaN: engine gives no SNR (windef)
    gu, gv = np.where(ok, dx, np.nan), np.where(ok, dy, np.nan)
    if max_speed is not None:
        ok &= pv.speed_test(gu / dt, gv / dt, max_speed)
    gu, gv = np.where(ok, dx, np.nan), np.where(ok, dy, np.nan)
    ok &= pv.global_std_test(gu, gv, params.std_threshold)
    gu, gv = np.where(ok, dx, np.nan), np.where(ok, dy, np.nan)
    ok &= pv.normalized_median_test(gu, gv, params.median_threshold)
    return ok


def analyze(
    frames: Iterable[tuple[float, np.ndarray]],
    params: PivParams,
    *,
    roi=None,
    mask: np.ndarray | None = None,
    max_speed_px_s: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
    on_pair: Callable | None = None,
    backend: str = "auto",
    select=None,
    carry=None,
    near=None,
    first_guess=None,
) -> PivResult:
    """Run PIV over consecutive frame pairs and average in time.

    Parameters
    ----------
    frames : iterable of (t_s, image), image gray HxW (uint8/float); consumed once, never stored.
        Consecutive frames form pairs; dt = t[i+1] - t[i] from the timestamps (s).
    params : PivParams.
    roi : (x0, y0, x1, y1) full-frame pixels (x1, y1 exclusive) or None for the whole frame.
    mask : bool HxW, True = invalid area; vectors whose window centre falls in it are invalid (never replaced),
        and its pixels are set to the frame mean before correlating.
    max_speed_px_s : (ny, nx) per-node speed limit in px/s (or a scalar), or None.
    progress : progress(done_pairs, total_pairs or 0).
    cancel : cancel() -> True raises fieldtool.errors.Cancelled within one pair.
    on_pair : on_pair(i, t_mid_s, x, y, u_px_s, v_px_s, valid) after each pair with vectors (i = the pair's index
        in the clip; ensemble: the sampled pairs only, see the module docstring).
    backend : "auto" (GPU when CuPy with a CUDA device is importable and passes its self-check, single pass
        only; else CPU), "cpu" or "gpu". See piv_gpu (unverified on real hardware).
    select : pair indices (0 = frames 0-1 of the stream) to correlate, or None for every pair. Frames that belong
        to no selected pair are read but not transformed, and the stream is left after the last selected pair.
        Every selected pair gets per-pair vectors. Used by ``piv_fast.converge`` (pairs added in rounds).
    carry : ``PivResult.carry`` of an earlier call on the same clip, geometry and parameters: its ensemble sums
        and per-pair fields are continued, so the result covers the pairs of all calls.
    near : (segments, reach_px) or None: only the nodes of pass k within ``reach_px[k]`` px of the segments (each
        two image points, px) are correlated (the fast path's band, ``piv_fast.node_reach_px``); the final pass'
        others have no vector, as masked nodes.
    first_guess : (xc, yc, dx, dy) or None: a displacement per pair (px; dx, dy (ny, nx)) on the regular grid of
        node centres xc (nx,), yc (ny,), e.g. ``planning.first_look``'s; the first pass moves each B window by
        it (CPU engine; module docstring). Others ignore it.

    Returns
    -------
    PivResult (px, px/s, image axes).
    """
    total = 0
    if hasattr(frames, "__len__"):
        total = max(len(frames) - max(1, int(params.frame_gap)), 0)  # type: ignore[arg-type]
    it = iter(frames)
    try:
        t_prev, first = next(it)
    except StopIteration:
        raise ParameterError("video: no frames in the selected time range; PIV needs at least 2 — check "
                             "video.start_s / video.end_s") from None
    first = _check_frame(0, first, None)
    shape = first.shape
    levels, box = _levels(shape, params, roi)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != shape:
            raise ParameterError(f"mask: {mask.shape[1]} x {mask.shape[0]} px does not match the "
                                 f"{shape[1]} x {shape[0]} px frames")
    if near is not None:
        segs, reach = near
        segs = [np.asarray(sg, float).reshape(2, 2) for sg in segs]
        if len(reach) != len(levels) or not segs:
            raise ValueError("analyze(near=...): one reach per pass and at least one segment")
        near = [near_nodes(lv, segs, r) for lv, r in zip(levels, reach)]  # per pass, the nodes correlated
    engine = _make_engine(backend, shape, params, levels, box, mask, near, first_guess)
    if not isinstance(engine, _Engine):  # only the CPU engine moves its windows by it
        first_guess = None
    nodes = _final_nodes(levels[-1], shape, mask, near, max_speed_px_s)

    ens = _Ensemble(engine, nodes.fin, params.snr_min) if params.averaging == "ensemble" else None
    if ens is not None:
        ens.remove_zero = params.remove_zero_peak
    # ensemble: per-pair vectors (inverse FFT + peaks of the final pass) only on every stride-th pair
    subsample = ens is not None and getattr(engine, "spectrum_only", False) and select is None
    stride = max(1, total // ENSEMBLE_PAIRS) if subsample else 1  # clip length unknown (total 0): grown below
    per_pair = {k: [] for k in ("u", "v", "t", "dt", "snr", "p2m", "peak", "index")}
    n_done = 0
    if carry is not None:  # continue an earlier call (select=): its ensemble sums and per-pair fields
        ens, per_pair, n_done = carry.ensemble, carry.per_pair, carry.n_pairs
        if ens is not None:
            ens.engine = engine
    wanted = None if select is None else frozenset(int(k) for k in select)
    loop = _PairLoop(engine, params, nodes, ens, wanted, subsample, stride, per_pair, total, shape)
    i = loop.run(it, first, t_prev, cancel, progress, on_pair)
    per_pair = loop.per_pair
    if wanted is not None:
        i = n_done + len(wanted & set(range(i)))
        if not per_pair["u"]:
            raise ParameterError("video: none of the selected pairs is in the clip; PIV needs at least 2 frames")
    return _time_average(per_pair, ens, nodes, params, i, wanted, first_guess)


@dataclass
class _Nodes:
    """The final pass' nodes: grid ``fin``, centres X, Y (px), ``node_mask`` (True: no vector: masked, or
    outside the band of ``near``, which is ``outside``), and the speed limit per node (px/s) or None."""

    fin: object
    X: np.ndarray
    Y: np.ndarray
    node_mask: np.ndarray
    outside: np.ndarray | None
    max_speed: np.ndarray | None


def _final_nodes(fin, shape, mask, near, max_speed_px_s) -> _Nodes:
    X, Y = np.meshgrid(fin.xc, fin.yc)
    node_mask = np.zeros((fin.ny, fin.nx), dtype=bool)
    if mask is not None:
        node_mask = mask[np.rint(Y).astype(int).clip(0, shape[0] - 1), np.rint(X).astype(int).clip(0, shape[1] - 1)]
    outside = None if near is None else ~near[-1]
    if outside is not None:
        node_mask = node_mask | outside
    if max_speed_px_s is not None:
        max_speed_px_s = np.broadcast_to(np.asarray(max_speed_px_s, dtype=np.float64), (fin.ny, fin.nx))
    return _Nodes(fin, X, Y, node_mask, outside, max_speed_px_s)


class _PairLoop:
    """The pairs of one :func:`analyze` call: each frame's spectra prepared once, kept for ``frame_gap``
    frames, each pair correlated (or skipped by ``select``), its vectors validated and collected in
    ``per_pair``; the ensemble sums grow on the way."""

    def __init__(self, engine, params: PivParams, nodes: _Nodes, ens, wanted, subsample: bool, stride: int,
                 per_pair: dict, total: int, shape):
        self.engine, self.params, self.nodes, self.ens, self.wanted = engine, params, nodes, ens, wanted
        self.subsample, self.stride, self.per_pair, self.total, self.shape = subsample, stride, per_pair, total, shape
        self.gap = max(1, int(params.frame_gap))

    def prep(self, k: int, img):
        """Frame k's spectra; with ``select``: None when no selected pair uses it (it may come undecoded),
        and only what a pair's second frame needs when it is not the first frame of a selected pair."""
        engine, wanted, gap = self.engine, self.wanted, self.gap
        if wanted is None:
            return engine.prepare(img)
        if k not in wanted and k - gap not in wanted:
            return None
        img = _check_frame(k, img, self.shape)
        if type(engine).prepare is not _Engine.prepare:
            return engine.prepare(img)
        return engine.prepare(img, as_a=k in wanted, as_b=k - gap in wanted)

    def run(self, it, first, t_prev, cancel, progress, on_pair) -> int:
        """Read the frames after ``first``; returns the number of pairs passed (correlated or skipped)."""
        wanted, gap, total, shape = self.wanted, self.gap, self.total, self.shape
        last_wanted = max(wanted) if wanted else -1
        history = deque([(self.prep(0, first), float(t_prev))], maxlen=gap)  # the last `gap` frames, oldest first
        t_last = float(t_prev)
        i = 0
        for i_frame, (t, img) in enumerate(it, start=1):
            if wanted is not None and i_frame - gap > last_wanted:  # hook of ``select``: no selected pair left
                break
            if cancel is not None and cancel():
                raise Cancelled(f"PIV cancelled by the user after {i} pairs")
            if wanted is None:
                img = _check_frame(i_frame, img, shape)
            t = float(t)
            if not t > t_last:
                raise InputFileError(
                    f"frames: timestamps must increase; frame {i_frame} is at {t:.6f} s after {t_last:.6f} s"
                )
            t_last = t
            cur = self.prep(i_frame, img)
            if len(history) < gap:  # the first frames only fill the history
                history.append((cur, t))
                continue
            prev, t_prev = history[0]
            if wanted is None or i in wanted:  # else the hook of ``select``: this pair is skipped
                self.pair(i, prev, cur, t_prev, t, cancel, on_pair)
            i += 1
            if progress is not None:
                progress(i, total)
            history.append((cur, t))
        if i == 0:
            if gap > 1:
                raise ParameterError(f"piv.frame_gap: {gap} frames between the images of a pair, but the selected "
                                     "time range holds no such pair; lower piv.frame_gap or widen video.start_s / "
                                     "video.end_s")
            raise ParameterError("video: only 1 frame in the selected time range; PIV needs at least 2 — widen "
                                 "video.start_s / video.end_s or lower video.step")
        return i

    def pair(self, i: int, prev, cur, t_prev: float, t: float, cancel, on_pair) -> None:
        """Correlate pair ``i`` (frames at ``t_prev`` and ``t`` s); its vectors (px/s) join ``per_pair``."""
        engine, params, nd, per_pair = self.engine, self.params, self.nodes, self.per_pair
        dt = t - t_prev
        cb = None
        if self.ens is not None:
            cb = self.ens.add_fn(dt, nd.node_mask)
        if self.subsample and i % self.stride:
            engine.correlate(prev, cur, cancel=cancel, ensemble=cb, peaks=False)
            return
        dx, dy, pk = engine.correlate(prev, cur, cancel=cancel, ensemble=cb)
        snr = pk.snr.reshape(dx.shape)
        ok = _pair_validity(dx, dy, pk.ok.reshape(dx.shape), snr, dt, params, nd.node_mask, nd.max_speed)
        u = np.where(ok, dx / dt, np.nan).astype(np.float32)
        v = np.where(ok, dy / dt, np.nan).astype(np.float32)
        tm = 0.5 * (t + t_prev)
        for key, val in (("u", u), ("v", v), ("t", tm), ("dt", dt), ("index", i),
                         ("snr", np.where(nd.node_mask, np.nan, snr).astype(np.float32)),
                         ("p2m", pk.p2m.reshape(dx.shape).astype(np.float32)),
                         ("peak", pk.peak.reshape(dx.shape).astype(np.float32))):
            per_pair[key].append(val)
        if self.subsample and not self.total and len(per_pair["u"]) >= 2 * ENSEMBLE_PAIRS:  # keep every other one
            self.per_pair = {key: val[::2] for key, val in per_pair.items()}
            self.stride *= 2
        if on_pair is not None:
            on_pair(i, tm, nd.X, nd.Y, u, v, ok)


def _time_average(per_pair: dict, ens, nodes: _Nodes, params: PivParams, n_pairs: int, wanted,
                  first_guess) -> PivResult:
    """The time-averaged field of the pairs (ensemble, mean or median), validated and filled, as a PivResult."""
    fin = nodes.fin
    u_pairs, v_pairs = np.stack(per_pair["u"]), np.stack(per_pair["v"])
    n_valid = np.sum(np.isfinite(u_pairs), axis=0)
    vf = n_valid / float(len(u_pairs))
    if nodes.outside is not None:
        vf = np.where(nodes.outside, np.nan, vf)
    with np.errstate(all="ignore"):
        snr_med = _nanmedian_t(np.stack(per_pair["snr"]))
        p2m_med = _nanmedian_t(np.stack(per_pair["p2m"]))
        peak_med = _nanmedian_t(np.stack(per_pair["peak"]))
    dts = np.asarray(per_pair["dt"])
    ens_snr = None
    if ens is not None:
        u_avg, v_avg, ens_ok, ens_snr = ens.result(keep=wanted is not None)
    else:
        if params.averaging == "mean":
            with np.errstate(all="ignore"):
                u_avg = np.nansum(u_pairs, axis=0, dtype=np.float64) / n_valid
                v_avg = np.nansum(v_pairs, axis=0, dtype=np.float64) / n_valid
        else:
            u_avg, v_avg = _nanmedian_t(u_pairs), _nanmedian_t(v_pairs)
        ens_ok = n_valid > 0
    u_avg, v_avg, valid, replaced = _finish_average(
        u_avg.astype(np.float64), v_avg.astype(np.float64), ens_ok, vf, nodes.node_mask, nodes.max_speed,
        float(np.median(dts)), params,
    )
    return PivResult(
        x=nodes.X, y=nodes.Y, u=u_avg, v=v_avg, valid=valid, valid_fraction=vf, u_pairs=u_pairs, v_pairs=v_pairs,
        t_pairs=np.asarray(per_pair["t"]), snr=snr_med, params=params, peak2mean=p2m_med, peak=peak_med,
        replaced=replaced, ensemble_snr=ens_snr, dt_s=dts, pair_index=np.asarray(per_pair["index"], dtype=np.int64),
        n_pairs=n_pairs, zero_peak_removed=None if ens is None else ens.zero_removed,
        first_guess=None if first_guess is None else _guess_at(fin, *first_guess, whole=False).reshape(fin.ny, fin.nx, 2),
        carry=_Carry(ens, per_pair, n_pairs) if wanted is not None else None,
    )

@dataclass
class _Carry:
    """What ``analyze(select=...)`` hands to its next call: the ensemble sums, per-pair fields, pairs done."""

    ensemble: object | None
    per_pair: dict
    n_pairs: int


def _nanmedian_t(stack: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN; NaN where a node has no value (no warning)."""
    if np.isfinite(stack).all():
        return np.median(stack, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(stack, axis=0)


def _finish_average(u, v, base_ok, vf, node_mask, max_speed, dt_med, params):
    """Validate the time-averaged field and replace isolated gaps from valid neighbours (masked nodes stay NaN)."""
    ok = base_ok & np.isfinite(u) & np.isfinite(v) & (vf >= params.min_valid_fraction) & ~node_mask
    ok &= pv.speed_test(np.where(ok, u, np.nan), np.where(ok, v, np.nan), max_speed)
    du, dv = np.where(ok, u * dt_med, np.nan), np.where(ok, v * dt_med, np.nan)
    ok &= pv.normalized_median_test(du, dv, params.median_threshold)
    u2, v2, replaced = pv.replace_invalid(np.where(ok, u, np.nan), np.where(ok, v, np.nan),
                                          keep_invalid=node_mask, min_neighbours=5, max_iter=1)
    valid = ok | replaced
    return np.where(valid, u2, np.nan), np.where(valid, v2, np.nan), valid, replaced


class _Ensemble:
    """SNR-weighted sum of the final pass' cross-spectra (or correlation planes) and predictors over all pairs.

    A pair with peaks weighs each node by clip(peak ratio - 1, 0, 10); a pair without (``peaks=None``, ensemble
    mode between the sampled pairs) by the node's mean weight over the pairs with peaks so far.
    """

    def __init__(self, engine, lv: _Level, snr_min: float):
        self.engine = engine
        self.lv = lv
        self.snr_min = snr_min
        self.spec = None
        self.wsum = np.zeros(lv.ny * lv.nx)
        self.px = np.zeros(lv.ny * lv.nx)
        self.py = np.zeros(lv.ny * lv.nx)
        self.wdt = np.zeros(lv.ny * lv.nx)
        self.wpk = np.zeros(lv.ny * lv.nx)  # sum of the weights of the pairs with peaks
        self.npk = 0
        self.remove_zero = False
        self.zero_removed = None

    def add_fn(self, dt: float, node_mask: np.ndarray):
        def add(cross, pred_x, pred_y, pk, scale=None):
            if pk is not None:
                w = np.clip(np.nan_to_num(pk.snr, nan=1.0) - 1.0, 0.0, 10.0)
                w[node_mask.ravel()] = 0.0
                self.wpk += w
                self.npk += 1
            else:
                w = self.wpk / max(self.npk, 1)
            if scale is not None:
                w = np.where(scale > 0, w, 0.0)  # featureless windows (texture gate) weigh nothing
            wf = w.astype(np.float32)
            if scale is not None:  # planes not normalised yet: unit-energy factors
                wf *= scale
            wf = wf.reshape((-1,) + (1,) * (cross.ndim - 1))
            to_device = getattr(self.engine, "to_device", None)  # GPU engine: weights go to the device
            cross *= wf if to_device is None else to_device(wf)
            if self.spec is None:
                self.spec = cross.copy()
            else:
                self.spec += cross
            self.wsum += w
            self.wdt += w * dt
            if pred_x is not None:
                self.px += w * pred_x.ravel()
                self.py += w * pred_y.ravel()

        return add

    def result(self, keep: bool = False):
        """Time-averaged field; ``keep``: leave the sums usable for more pairs (the inverse FFT works in place)."""
        lv = self.lv
        spec = self.spec.copy() if keep else self.spec  # the inverse FFT works in place
        if self.remove_zero and type(self.engine) is _Engine and len(self.engine.levels) > 1:
            from fieldtool.processing import piv_peaks

            corr = self.engine.ensemble_planes(spec)
            with np.errstate(all="ignore"):
                self.zero_removed = piv_peaks.blank_zero(corr, lv.margin, self.px / self.wsum, self.py / self.wsum)
            self.zero_removed = self.zero_removed.reshape(lv.ny, lv.nx)
            pk = _find_peaks(corr, lv.margin)
        else:
            pk = self.engine.ensemble_peaks(spec)
        with np.errstate(all="ignore"):
            dt = self.wdt / self.wsum
            dx = pk.dx + self.px / self.wsum
            dy = pk.dy + self.py / self.wsum
            u, v = dx / dt, dy / dt
        ok = (self.wsum > 0) & pk.ok & (np.nan_to_num(pk.snr) >= self.snr_min)
        shp = (lv.ny, lv.nx)
        return u.reshape(shp), v.reshape(shp), ok.reshape(shp), pk.snr.reshape(shp)


def _make_engine(backend, shape, params, levels, box, mask, near=None, guess=None):
    """The engine of ``params.engine`` / ``backend``. ``near`` (per level, the nodes near the section; the others
    are skipped) is only a saving of the CPU engine; the others correlate every node and ``analyze`` drops the far ones. ``guess``
    (first-pass window offsets) only the CPU engine uses."""
    if params.engine == "openpiv":
        return _OpenPivEngine(shape, params, levels, box, mask)
    if backend not in ("auto", "cpu", "gpu"):
        raise ParameterError(f"piv backend: {backend!r} is not one of auto, cpu, gpu")
    if guess is not None and backend == "gpu":
        raise ParameterError("piv backend: gpu asked for, but the first pass starts from the first look's field, which "
                             "only the CPU engine does; set piv.search_px to search a wider area instead")
    if backend in ("auto", "gpu") and guess is None:
        from fieldtool.processing import piv_gpu

        if piv_gpu.usable_for(params) and piv_gpu.available():
            return piv_gpu.GpuEngine(shape, params, levels, box, mask)
        if backend == "gpu":
            raise ParameterError("piv backend: gpu asked for, but it needs CuPy with a CUDA device (checked against "
                                 "the CPU engine) and piv.passes = 1")
    return _Engine(shape, params, levels, box, mask, near, guess)


class _OpenPivEngine(_Engine):
    """Same pairs, grid and outputs through OpenPIV: ``pyprocess.extended_search_area_piv`` for one pass,
    ``windef.simple_multipass`` (OpenPIV's window deformation and its own validation) for several."""

    def __init__(self, shape, params, levels, box, mask):
        super().__init__(shape, params, levels, box, mask)
        if params.averaging == "ensemble" and len(levels) > 1:
            raise ParameterError(
                "piv.averaging: ensemble is not available with piv.engine = openpiv and piv.passes > 1; "
                "use mean or median, or piv.engine = fieldtool"
            )

    def prepare(self, frame: np.ndarray) -> _Frame:
        return _Frame(img=self._masked_crop(frame), spec_a=[], spec_b0=None)

    def _sub(self, img: np.ndarray, lv: _Level, size: int) -> np.ndarray:
        """Part of the crop whose OpenPIV grid (windows of ``size`` from 0, step lv.step) is our level grid."""
        oy, ox = self._offsets(lv)
        m = (size - lv.w) // 2
        return img[oy - m : oy - m + lv.step * (lv.ny - 1) + size, ox - m : ox - m + lv.step * (lv.nx - 1) + size]

    def correlate(self, a: _Frame, b: _Frame, cancel=None, ensemble=None):
        import contextlib
        import io

        from openpiv import pyprocess, windef
        from openpiv.settings import PIVSettings

        lv = self.levels[-1]
        n = lv.ny * lv.nx
        if len(self.levels) == 1:
            fa, fb = self._sub(a.img, lv, lv.s), self._sub(b.img, lv, lv.s)
            corr = self._planes(fa, fb, lv)
            u, v = pyprocess.correlation_to_displacement(corr, lv.ny, lv.nx, subpixel_method="gaussian")
            snr = pyprocess.sig2noise_ratio(corr, sig2noise_method="peak2peak", width=2).ravel()
            peak = corr.reshape(n, -1).max(axis=1)
            if ensemble is not None:
                ensemble(corr, None, None, None if snr is None else _Peaks(
                    dx=u.ravel(), dy=v.ravel(), peak=peak, snr=snr, p2m=snr, ok=np.isfinite(snr)))
        else:
            st = PIVSettings()
            st.windowsizes = tuple(L.w for L in self.levels)
            st.overlap = tuple(L.w - L.step for L in self.levels)
            st.num_iterations = len(self.levels)
            with contextlib.redirect_stdout(io.StringIO()):
                fa, fb = self._sub(a.img, lv, lv.w), self._sub(b.img, lv, lv.w)
                _, _, u, v, flags = windef.simple_multipass(fa, fb, st)
            v = -v  # simple_multipass negates v (tools.transform_coordinates; rows stay in image order)
            snr = np.where(np.asarray(flags).ravel() > 0, 0.0, np.nan)
            peak = np.full(n, np.nan)
        dx, dy = np.asarray(u, dtype=np.float64).reshape(lv.ny, lv.nx), np.asarray(v, dtype=np.float64).reshape(
            lv.ny, lv.nx)
        ok = np.isfinite(dx.ravel()) & np.isfinite(dy.ravel()) & (np.nan_to_num(snr, nan=np.inf) > 0)
        return dx, dy, _Peaks(dx=dx.ravel(), dy=dy.ravel(), peak=peak, snr=snr, p2m=np.full(n, np.nan), ok=ok)

    @staticmethod
    def _planes(fa: np.ndarray, fb: np.ndarray, lv: _Level) -> np.ndarray:
        """OpenPIV's correlation planes, as in extended_search_area_piv (circular FFT, fft-shifted)."""
        from openpiv import pyprocess

        aa = pyprocess.sliding_window_array(fa, (lv.s, lv.s), (lv.s - lv.step, lv.s - lv.step))
        bb = pyprocess.sliding_window_array(fb, (lv.s, lv.s), (lv.s - lv.step, lv.s - lv.step))
        if lv.s > lv.w:
            aa = pyprocess.normalize_intensity(aa)
            bb = pyprocess.normalize_intensity(bb)
            m = np.zeros((lv.s, lv.s), dtype=aa.dtype)
            m[lv.margin : lv.margin + lv.w, lv.margin : lv.margin + lv.w] = 1
            aa = aa * m
        return pyprocess.fft_correlate_images(aa, bb, correlation_method="circular", normalized_correlation=False)

    def ensemble_peaks(self, acc: np.ndarray) -> _Peaks:
        from openpiv import pyprocess

        lv = self.levels[-1]
        u, v = pyprocess.correlation_to_displacement(acc, lv.ny, lv.nx, subpixel_method="gaussian")
        snr = pyprocess.sig2noise_ratio(acc, sig2noise_method="peak2peak", width=2).ravel()
        ok = np.isfinite(u.ravel()) & np.isfinite(v.ravel())
        return _Peaks(dx=u.ravel(), dy=v.ravel(), peak=acc.reshape(len(snr), -1).max(axis=1), snr=snr,
                      p2m=np.full(len(snr), np.nan), ok=ok)
