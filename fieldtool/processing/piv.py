"""PIV correlation engine: frame pairs -> per-pair and time-averaged vector fields with quality.

Thesis 2.2.4 (FFT cross-correlation, multi-pass, sub-pixel, validation), 6.2 and 9.2.8.

How it works
------------
* Every frame is cut into interrogation windows with a strided view (no copy of the frame), each window is
  normalised (zero mean, unit energy) and all windows go through one batched real FFT (``scipy.fft.rfft2``,
  float32, all cores). A frame's window spectra are computed once and serve the pair before it (as frame B) and
  the pair after it (as frame A).
* Correlation plane of a pair = inverse FFT of ``conj(A) * B``; the displacement is the highest peak, refined by a
  Gaussian 3-point fit (parabolic where a value is not positive). Quality per vector: peak-to-second-peak ratio
  (outside a 5 x 5 neighbourhood of the first), peak-to-mean ratio and the peak value (a correlation coefficient, 1 = perfect match). The planes have zero mean (the windows do), so the
  peak-to-mean ratio is taken on the plane's mean energy: peak / root-mean-square.
* ``search_px`` larger than the first window: the A window is zero-padded inside a B window of the search size, so
  displacements up to (search - window) / 2 are found without wrap-around.
* ``passes > 1``: the first pass uses windows ``window_px * 2**(passes-1)``; each later pass deforms the second frame
  with ``cv2.remap`` (Lanczos, 8 x 8) by the previous pass' validated field, interpolated bicubically to every
  pixel, correlates the smaller windows and adds the residual to the predictor. The first frame's window spectra
  are not deformed, so they are still computed once per frame.
* Averaging: ``ensemble`` sums the cross-spectra of all pairs per node, weighted by their signal-to-noise
  (weight = clip(peak ratio - 1, 0, 10)), and takes one peak per node at the end (one inverse FFT for the clip);
  ``mean``/``median`` average the validated per-pair vectors.
* Frames are consumed as a stream: only the previous frame's spectra and one accumulator are held, plus the
  per-pair fields the result has to return (2 x 4 bytes per node and pair).

Conventions: image axes, +x right, +y down, origin at the centre of the top-left pixel; u, v in px/s from the
frame timestamps. A node's position is the centre of its final interrogation window.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from typing import Callable, Iterable

import cv2
import numpy as np
import scipy.fft

from fieldtool.errors import Cancelled, InputFileError, ParameterError
from fieldtool.processing import piv_validate as pv

AVERAGING = ("ensemble", "mean", "median")
ENGINES = ("fieldtool", "openpiv")
_WORKERS = max(1, os.cpu_count() or 1)
_SNR_CAP = 1000.0  # peak ratio reported when the plane has no positive second peak


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


@dataclass
class PivResult:
    """Time-averaged and per-pair vector fields on the node grid (image axes, px/s)."""

    x: np.ndarray  # (ny, nx) node centres, px
    y: np.ndarray
    u: np.ndarray  # (ny, nx) time-averaged velocity, px/s; NaN where invalid
    v: np.ndarray
    valid: np.ndarray  # (ny, nx) bool (measured or replaced from valid neighbours)
    valid_fraction: np.ndarray  # (ny, nx) fraction of pairs in which the node was valid
    u_pairs: np.ndarray  # (n_pairs, ny, nx) px/s, NaN = invalid
    v_pairs: np.ndarray
    t_pairs: np.ndarray  # (n_pairs,) mid-times, s
    snr: np.ndarray  # (ny, nx) median peak-to-second-peak ratio over the pairs
    params: PivParams
    peak2mean: np.ndarray | None = None  # (ny, nx) median peak-to-mean ratio over the pairs
    peak: np.ndarray | None = None  # (ny, nx) median correlation peak value (correlation coefficient)
    replaced: np.ndarray | None = None  # (ny, nx) bool, average filled in from valid neighbours
    ensemble_snr: np.ndarray | None = None  # (ny, nx) peak ratio of the ensemble plane (averaging = ensemble)
    dt_s: np.ndarray | None = None  # (n_pairs,) time between the frames of each pair, s


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


def _window_spectra(img: np.ndarray, oy: int, ox: int, lv: _Level, size: int) -> np.ndarray:
    """Spectra (n, s, s//2+1) of the windows of side ``size`` at crop offset (oy, ox), each normalised to zero mean
    and unit energy, zero-padded to the level's search side ``lv.s`` when ``size < lv.s``.

    With ``size == lv.s`` the normalisation is done on the spectrum (DC set to 0, energy by Parseval), which saves
    two passes over the windows. A ``size == lv.s > lv.w`` window (search area of frame B) is scaled to the energy
    of a ``lv.w`` window so its correlation values stay comparable to correlation coefficients.
    """
    s = lv.s
    view = _window_view(img, oy, ox, lv, size)
    n = lv.ny * lv.nx
    if size == s:
        spec = scipy.fft.rfft2(view, axes=(2, 3), workers=_WORKERS).reshape(n, s, s // 2 + 1)
        spec[:, 0, 0] = 0.0  # zero mean
        fv = spec.view(np.float32)  # (n, s, 2 * (s // 2 + 1)): re, im interleaved
        tot = np.einsum("nij,nij->n", fv, fv)
        edge = np.einsum("nij,nij->n", fv[:, :, 0:2], fv[:, :, 0:2])
        edge += np.einsum("nij,nij->n", fv[:, :, -2:], fv[:, :, -2:])  # Nyquist column (s even)
        energy = (2.0 * tot - edge) / float(s * s)  # Parseval for the half spectrum = sum (x - mean)^2
        scale = np.float32(lv.w / s) if s != lv.w else np.float32(1.0)
        norm = np.sqrt(np.maximum(energy, 1e-12)).astype(np.float32) * scale
        inv = np.where(energy > 1e-6, 1.0 / norm, 0.0).astype(np.float32)  # featureless window: no correlation
        spec *= inv[:, None, None]
        return spec
    win = view.reshape(n, size, size)  # copy
    win -= win.mean(axis=(1, 2), dtype=np.float32)[:, None, None]
    energy = np.einsum("nij,nij->n", win, win)
    inv = np.where(energy > 1e-6, 1.0 / np.sqrt(np.maximum(energy, 1e-12)), 0.0).astype(np.float32)
    win *= inv[:, None, None]
    return scipy.fft.rfft2(win, s=(s, s), axes=(1, 2), workers=_WORKERS)


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


def _find_peaks(corr: np.ndarray, margin: int) -> _Peaks:
    """Peaks of correlation planes (n, s, s) in FFT order (index k <-> displacement k - margin, circular).

    The planes are modified in place (the first peak is blanked to find the second).
    """
    n, s, _ = corr.shape
    rows = np.arange(n)
    flat = corr.reshape(n, s * s)
    rms = np.sqrt(np.einsum("ij,ij->i", flat, flat) / float(s * s))  # the plane has zero mean
    if margin > 0:
        span = 2 * margin + 1
        region = corr[:, :span, :span].reshape(n, span * span)
        ky, kx = np.divmod(region.argmax(axis=1), span)
    else:
        span = s
        ky, kx = np.divmod(flat.argmax(axis=1), s)
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
    # second peak: the highest local maximum outside a 5 x 5 neighbourhood of the first. Only local
    # maxima count: elongated particle images (oblique views) give a broad first peak whose shoulder
    # is not a second peak.
    plane = corr[:, :span, :span] if margin > 0 else corr
    local_max = np.ones(plane.shape, bool)
    for dy_, dx_ in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        local_max &= plane >= np.roll(plane, (dy_, dx_), axis=(1, 2))
    off = np.arange(-2, 3)
    yy = (ky[:, None, None] + off[None, :, None]) % s
    xx = (kx[:, None, None] + off[None, None, :]) % s
    corr[rows[:, None, None], yy, xx] = -np.inf
    p2 = np.where(local_max, plane, -np.inf).reshape(n, -1).max(axis=1).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(p2 > 0, c / p2, _SNR_CAP)
        p2m = c / rms
    ok = (c > 0) & (rms > 0) & ~edge
    snr = np.where(ok, np.minimum(snr, _SNR_CAP), np.nan)
    p2m = np.where(ok, p2m, np.nan)
    return _Peaks(dx=ix + sx, dy=iy + sy, peak=c, snr=snr, p2m=p2m, ok=ok)


# --------------------------------------------------------------------------------------------- the engine


@dataclass
class _Frame:
    """What the engine keeps of one frame: its crop (multi-pass only) and window spectra."""

    img: np.ndarray | None
    spec_a: list  # per level: spectra of the normalised A windows (padded to the level's search side)
    spec_b0: np.ndarray  # first level: spectra of the B windows (search side)


class _Engine:
    """Correlation of consecutive frames on fixed pass geometry (CPU, scipy.fft)."""

    def __init__(self, shape, params: PivParams, levels: list[_Level], box, mask: np.ndarray | None):
        self.p = params
        self.levels = levels
        self.h, self.w = shape
        x0, y0, x1, y1 = box
        m = levels[0].margin
        self.cx0, self.cy0 = x0 - m, y0 - m  # crop origin in full-frame px (may be negative: padded)
        self.cw, self.ch = (x1 - x0) + 2 * m, (y1 - y0) + 2 * m
        self.box = box
        self.mask_crop = None if mask is None else self._crop(mask.astype(np.uint8), 0) > 0
        if mask is not None and not self.mask_crop.any():
            self.mask_crop = None
        self._maps: dict = {}

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

    def prepare(self, frame: np.ndarray) -> _Frame:
        """Crop, fill the mask with the frame mean, and compute the window spectra of all levels."""
        f = frame if frame.dtype == np.float32 else frame.astype(np.float32)
        x0, y0, x1, y1 = self.box
        fill = float(f[y0:y1, x0:x1].mean())
        img = self._crop(f, fill)
        if self.mask_crop is not None:
            img = img.copy()
            img[self.mask_crop] = fill
        spec_a = []
        for lv in self.levels:
            oy, ox = self._offsets(lv)
            spec_a.append(_window_spectra(img, oy, ox, lv, lv.w))
        lv0 = self.levels[0]
        if lv0.s == lv0.w:
            spec_b0 = spec_a[0]
        else:
            oy, ox = self._offsets(lv0)
            spec_b0 = _window_spectra(img, oy - lv0.margin, ox - lv0.margin, lv0, lv0.s)
        return _Frame(img=img if len(self.levels) > 1 else None, spec_a=spec_a, spec_b0=spec_b0)

    def _dense_maps(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pixel grid of the crop and its fractional node indices on level k-1 (cached)."""
        if k not in self._maps:
            prev = self.levels[k - 1]
            xs = np.arange(self.cw, dtype=np.float32)
            ys = np.arange(self.ch, dtype=np.float32)
            gx = (xs + self.cx0 - prev.xc[0]) / prev.step
            gy = (ys + self.cy0 - prev.yc[0]) / prev.step
            fx, fy = np.meshgrid(gx.astype(np.float32), gy.astype(np.float32))
            px, py = np.meshgrid(xs, ys)
            self._maps[k] = (px, py, fx, fy)
        return self._maps[k]

    def _node_predictor(self, k: int, du: np.ndarray, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate a level k-1 field (ny, nx) at the node centres of level k (bicubic, edges replicated)."""
        prev, lv = self.levels[k - 1], self.levels[k]
        gx = ((lv.xc - prev.xc[0]) / prev.step).astype(np.float32)
        gy = ((lv.yc - prev.yc[0]) / prev.step).astype(np.float32)
        fx, fy = np.meshgrid(gx, gy)
        field2 = np.dstack([du, dv]).astype(np.float32)
        out = cv2.remap(field2, fx, fy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return out[..., 0].astype(np.float64), out[..., 1].astype(np.float64)

    def ensemble_peaks(self, acc: np.ndarray) -> _Peaks:
        """Peaks of the ensemble correlation from the summed cross-spectra of the final pass."""
        lv = self.levels[-1]
        return _find_peaks(scipy.fft.irfft2(acc, s=(lv.s, lv.s), axes=(1, 2), workers=_WORKERS), lv.margin)

    def correlate(self, a: _Frame, b: _Frame, cancel=None, ensemble=None):
        """Correlate frame a with b through all passes.

        Returns (dx, dy, peaks) of the final level, dx/dy the total displacement (px) per node (flattened), and
        the final-level predictor (px, zeros for a single pass). ``ensemble(cross, pred_dx, pred_dy, peaks)``
        is called with the final level's cross-spectrum before it is discarded.
        """
        pred_x = pred_y = None
        for k, lv in enumerate(self.levels):
            if k == 0:
                cross = np.conj(a.spec_a[0])
                cross *= b.spec_b0
            else:
                if cancel is not None and cancel():
                    raise Cancelled("PIV cancelled by the user")
                px, py, fx, fy = self._dense_maps(k)
                field2 = np.dstack([du, dv]).astype(np.float32)
                dense = cv2.remap(field2, fx, fy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
                bdef = cv2.remap(b.img, px + dense[..., 0], py + dense[..., 1], cv2.INTER_LANCZOS4,
                                 borderMode=cv2.BORDER_REPLICATE)
                pred_x, pred_y = self._node_predictor(k, du, dv)
                oy, ox = self._offsets(lv)
                cross = np.conj(a.spec_a[k])
                cross *= _window_spectra(bdef, oy, ox, lv, lv.w)
            corr = scipy.fft.irfft2(cross, s=(lv.s, lv.s), axes=(1, 2), workers=_WORKERS)
            pk = _find_peaks(corr, lv.margin)
            dx, dy = pk.dx.reshape(lv.ny, lv.nx), pk.dy.reshape(lv.ny, lv.nx)
            if pred_x is not None:
                dx = dx + pred_x
                dy = dy + pred_y
            if k == len(self.levels) - 1:
                if ensemble is not None:
                    ensemble(cross, pred_x, pred_y, pk)
                return dx, dy, pk
            # predictor for the next pass: validated and filled
            good = pk.ok.reshape(lv.ny, lv.nx) & (pk.snr.reshape(lv.ny, lv.nx) >= 1.0)
            gu, gv = np.where(good, dx, np.nan), np.where(good, dy, np.nan)
            ok = pv.normalized_median_test(gu, gv, self.p.median_threshold)
            du, dv = pv.fill_all(np.where(ok, gu, np.nan), np.where(ok, gv, np.nan))
        raise AssertionError("unreachable")


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
    on_pair : on_pair(i, t_mid_s, x, y, u_px_s, v_px_s, valid) after each pair.
    backend : "auto" (GPU when CuPy with a CUDA device is importable and passes its self-check, single pass
        only; else CPU), "cpu" or "gpu". See piv_gpu (unverified on real hardware).

    Returns
    -------
    PivResult (px, px/s, image axes).
    """
    total = 0
    if hasattr(frames, "__len__"):
        total = max(len(frames) - 1, 0)  # type: ignore[arg-type]
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
    engine = _make_engine(backend, shape, params, levels, box, mask)
    fin = levels[-1]
    X, Y = np.meshgrid(fin.xc, fin.yc)
    node_mask = np.zeros((fin.ny, fin.nx), dtype=bool)
    if mask is not None:
        node_mask = mask[np.rint(Y).astype(int).clip(0, shape[0] - 1), np.rint(X).astype(int).clip(0, shape[1] - 1)]
    if max_speed_px_s is not None:
        max_speed_px_s = np.broadcast_to(np.asarray(max_speed_px_s, dtype=np.float64), (fin.ny, fin.nx))

    ens = _Ensemble(engine, fin, params.snr_min) if params.averaging == "ensemble" else None
    u_list, v_list, t_list, dt_list, snr_list, p2m_list, peak_list = [], [], [], [], [], [], []
    prev = engine.prepare(first)
    t_prev = float(t_prev)
    i = 0
    for i_frame, (t, img) in enumerate(it, start=1):
        if cancel is not None and cancel():
            raise Cancelled(f"PIV cancelled by the user after {i} pairs")
        img = _check_frame(i_frame, img, shape)
        t = float(t)
        dt = t - t_prev
        if not dt > 0:
            raise InputFileError(
                f"frames: timestamps must increase; frame {i_frame} is at {t:.6f} s after {t_prev:.6f} s"
            )
        cur = engine.prepare(img)
        cb = None
        if ens is not None:
            cb = ens.add_fn(dt, node_mask)
        dx, dy, pk = engine.correlate(prev, cur, cancel=cancel, ensemble=cb)
        snr = pk.snr.reshape(dx.shape)
        ok = _pair_validity(dx, dy, pk.ok.reshape(dx.shape), snr, dt, params, node_mask, max_speed_px_s)
        u = np.where(ok, dx / dt, np.nan).astype(np.float32)
        v = np.where(ok, dy / dt, np.nan).astype(np.float32)
        tm = 0.5 * (t + t_prev)
        u_list.append(u)
        v_list.append(v)
        t_list.append(tm)
        dt_list.append(dt)
        snr_list.append(np.where(node_mask, np.nan, snr).astype(np.float32))
        p2m_list.append(pk.p2m.reshape(dx.shape).astype(np.float32))
        peak_list.append(pk.peak.reshape(dx.shape).astype(np.float32))
        i += 1
        if on_pair is not None:
            on_pair(i - 1, tm, X, Y, u, v, ok)
        if progress is not None:
            progress(i, total)
        prev, t_prev = cur, t
    if i == 0:
        raise ParameterError("video: only 1 frame in the selected time range; PIV needs at least 2 — widen "
                             "video.start_s / video.end_s or lower video.step")

    u_pairs, v_pairs = np.stack(u_list), np.stack(v_list)
    n_valid = np.sum(np.isfinite(u_pairs), axis=0)
    vf = n_valid / float(i)
    with np.errstate(all="ignore"):
        snr_med = _nanmedian_t(np.stack(snr_list))
        p2m_med = _nanmedian_t(np.stack(p2m_list))
        peak_med = _nanmedian_t(np.stack(peak_list))
    dts = np.asarray(dt_list)
    ens_snr = None
    if ens is not None:
        u_avg, v_avg, ens_ok, ens_snr = ens.result()
    else:
        if params.averaging == "mean":
            with np.errstate(all="ignore"):
                u_avg = np.nansum(u_pairs, axis=0, dtype=np.float64) / n_valid
                v_avg = np.nansum(v_pairs, axis=0, dtype=np.float64) / n_valid
        else:
            u_avg, v_avg = _nanmedian_t(u_pairs), _nanmedian_t(v_pairs)
        ens_ok = n_valid > 0
    u_avg, v_avg, valid, replaced = _finish_average(
        u_avg.astype(np.float64), v_avg.astype(np.float64), ens_ok, vf, node_mask, max_speed_px_s,
        float(np.median(dts)), params,
    )
    return PivResult(
        x=X, y=Y, u=u_avg, v=v_avg, valid=valid, valid_fraction=vf, u_pairs=u_pairs, v_pairs=v_pairs,
        t_pairs=np.asarray(t_list), snr=snr_med, params=params, peak2mean=p2m_med, peak=peak_med,
        replaced=replaced, ensemble_snr=ens_snr, dt_s=dts,
    )


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
    """SNR-weighted sum of the final pass' cross-spectra (or correlation planes) and predictors over all pairs."""

    def __init__(self, engine, lv: _Level, snr_min: float):
        self.engine = engine
        self.lv = lv
        self.snr_min = snr_min
        self.spec = None
        self.wsum = np.zeros(lv.ny * lv.nx)
        self.px = np.zeros(lv.ny * lv.nx)
        self.py = np.zeros(lv.ny * lv.nx)
        self.wdt = np.zeros(lv.ny * lv.nx)

    def add_fn(self, dt: float, node_mask: np.ndarray):
        def add(cross, pred_x, pred_y, pk):
            w = np.clip(np.nan_to_num(pk.snr, nan=1.0) - 1.0, 0.0, 10.0)
            w[node_mask.ravel()] = 0.0
            wf = w.astype(np.float32).reshape((-1,) + (1,) * (cross.ndim - 1))
            to_device = getattr(self.engine, "to_device", None)  # GPU engine: weights go to the device
            cross *= wf if to_device is None else to_device(wf)
            if self.spec is None:
                self.spec = cross
            else:
                self.spec += cross
            self.wsum += w
            self.wdt += w * dt
            if pred_x is not None:
                self.px += w * pred_x.ravel()
                self.py += w * pred_y.ravel()

        return add

    def result(self):
        lv = self.lv
        pk = self.engine.ensemble_peaks(self.spec)
        with np.errstate(all="ignore"):
            dt = self.wdt / self.wsum
            dx = pk.dx + self.px / self.wsum
            dy = pk.dy + self.py / self.wsum
            u, v = dx / dt, dy / dt
        ok = (self.wsum > 0) & pk.ok & (np.nan_to_num(pk.snr) >= self.snr_min)
        shp = (lv.ny, lv.nx)
        return u.reshape(shp), v.reshape(shp), ok.reshape(shp), pk.snr.reshape(shp)


def _make_engine(backend, shape, params, levels, box, mask):
    if params.engine == "openpiv":
        return _OpenPivEngine(shape, params, levels, box, mask)
    if backend not in ("auto", "cpu", "gpu"):
        raise ParameterError(f"piv backend: {backend!r} is not one of auto, cpu, gpu")
    if backend in ("auto", "gpu"):
        from fieldtool.processing import piv_gpu

        if piv_gpu.usable_for(params) and piv_gpu.available():
            return piv_gpu.GpuEngine(shape, params, levels, box, mask)
        if backend == "gpu":
            raise ParameterError("piv backend: gpu asked for, but it needs CuPy with a CUDA device (checked against "
                                 "the CPU engine) and piv.passes = 1")
    return _Engine(shape, params, levels, box, mask)


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
        f = frame if frame.dtype == np.float32 else frame.astype(np.float32)
        x0, y0, x1, y1 = self.box
        fill = float(f[y0:y1, x0:x1].mean())
        img = self._crop(f, fill)
        if self.mask_crop is not None:
            img = img.copy()
            img[self.mask_crop] = fill
        return _Frame(img=img, spec_a=[], spec_b0=None)

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
