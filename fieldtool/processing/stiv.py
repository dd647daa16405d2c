"""STIV: space-time image velocimetry along search lines across the section of interest.

A search line is a straight segment on the water plane, parallel to the flow (by default along the
section's downstream normal), centred on a subsection of the section. Each working frame is sampled
along every line (bilinear, through the ortho mapping: the line is laid out in metres on the water
plane and placed in image pixels with the inverse homography, so its samples are equally spaced in
metres). Stacking the samples of successive frames gives one space-time image (STI) per line: rows are
times (s), columns are positions along the line (m). A tracer or a texture drifting at ``v`` m/s along
the line draws a streak ``s = s0 + v t``; the orientation of the STI's texture is the velocity.

Two orientation estimators are provided (see ``benchmarks/stiv_accuracy.py`` for their errors):

- ``"fft"`` (default): the STI's 2-D autocorrelation (FFT power spectrum, inverse FFT; the
  Wiener-Khinchin form of Fujita's 2-D FFT method), integrated along straight lines through the origin
  (a Radon projection over 1..K row lags); the angle of the best line is the velocity. Works at any
  streak slope, both signs, and its normalised peak height is the confidence (0..1: how much of the
  texture is carried unchanged along the line).
- ``"tensor"``: the classical structure tensor of the STI (Gaussian-smoothed Scharr gradients, summed
  over the image); confidence is the tensor's coherence. Biased once streaks move more than ~1 px per
  row (temporal derivatives alias), which the FFT method is not.

Before either, the STI is put on a uniform time grid from the frames' own timestamps (dropped or
irregular frames are interpolated, never assumed at 1/fps), each column's running mean over
``HIGHPASS_S`` (1 s) and each row's mean are removed (static texture, glints switching in place, slowly
changing ripple fields and global brightness changes draw no streak; on the hard presets this
high-pass took the ripples scene from -10 % to -2 % and changed no other scene by more than 0.5 %).

Units: metres, seconds, m/s. World axes as :mod:`fieldtool.processing.ortho`; image x right, y down.
Velocities along a line are signed: positive in the line's direction.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.fft as sfft
from scipy.ndimage import uniform_filter1d

from fieldtool.errors import ParameterError
from fieldtool.processing import piv_engine
from fieldtool.processing.ortho import OrthoMapping

METHODS = ("fft", "tensor")


@dataclass
class StivLine:
    """One search line: ``sub`` is the subsection it samples (0-based, in the geometry it was built on).

    ``center_m`` (2,) and ``direction`` (2,) unit vector on the water plane (m); ``ds_m`` sample
    spacing (m); ``pts_px`` (width, n, 2) sample positions in working-image pixels (``width`` parallel
    rows ``ds_m`` apart, averaged); ``angle_deg`` the turn of
    ``direction`` from the section normal (counter-clockwise seen from above).
    """

    sub: int
    center_m: np.ndarray
    direction: np.ndarray
    length_m: float
    ds_m: float
    pts_px: np.ndarray
    angle_deg: float = 0.0


def _rot(v: np.ndarray, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def build_lines(
    p_world: np.ndarray,
    normal: np.ndarray,
    mapping: OrthoMapping,
    n_sub: int,
    *,
    length_m: float = 3.0,
    lines_per_sub: int = 3,
    angles_deg=(0.0,),
    image_shape: tuple[int, int] | None = None,
    valid: np.ndarray | None = None,
    px_per_sample: float = 1.0,
    width: int = 3,
) -> list[StivLine]:
    """Search lines across the section, ``lines_per_sub`` per subsection and per angle.

    Parameters
    ----------
    p_world : (2, 2) m, the section's left then right water edge on the water plane.
    normal : (2,) downstream unit normal of the section (world).
    mapping : image <-> water-plane mapping.
    n_sub : number of subsections; line centres sit at the fractions (i + (j + 0.5) / lines_per_sub) / n_sub.
    length_m : line length (m), centred on the section.
    lines_per_sub : lines per subsection (spread evenly across it).
    angles_deg : turns of the line direction from the normal (deg, counter-clockwise from above); 0 = normal.
    image_shape : (H, W) of the working frames; samples outside are cut (the longest inside run is kept).
    valid : optional bool (H, W), False where samples must not be taken (outside the ROI, masks).
    px_per_sample : spacing of the samples in image pixels at the line's centre (1 = one per pixel).
    width : parallel sample rows averaged across the line (one sample spacing apart): a band, so a tracer
        crossing a line slightly off the flow stays in it longer.

    Returns
    -------
    list of StivLine (lines shorter than 8 samples after cutting are dropped).
    """
    if length_m <= 0 or lines_per_sub < 1 or n_sub < 1:
        raise ParameterError("stiv.line_length_m and stiv.lines_per_sub must be positive")
    p_world = np.asarray(p_world, float)
    d = p_world[1] - p_world[0]
    lines = []
    for i in range(n_sub):
        for j in range(lines_per_sub):
            c = p_world[0] + d * (i + (j + 0.5) / lines_per_sub) / n_sub
            for ang in angles_deg:
                e = _rot(np.asarray(normal, float), float(ang))
                e /= np.hypot(*e)
                ends = mapping.world_to_image(np.array([c - 0.5 * length_m * e, c + 0.5 * length_m * e]))
                n = int(np.ceil(np.hypot(*(ends[1] - ends[0])) / px_per_sample)) + 1
                if n < 8:
                    continue
                s = np.linspace(-0.5 * length_m, 0.5 * length_m, n)
                ds = length_m / (n - 1)
                across = (np.arange(width) - (width - 1) / 2) * ds
                e_perp = np.array([-e[1], e[0]])
                pw = c + s[None, :, None] * e + across[:, None, None] * e_perp
                px = mapping.world_to_image(pw.reshape(-1, 2)).reshape(width, n, 2)
                ok = np.all(np.isfinite(px), axis=(0, 2))
                if image_shape is not None:
                    h, w = image_shape
                    ok &= np.all(
                        (px[..., 0] >= 0) & (px[..., 0] <= w - 1) & (px[..., 1] >= 0) & (px[..., 1] <= h - 1), axis=0
                    )
                if valid is not None and ok.any():
                    ix = np.clip(np.rint(px[..., 0]).astype(int), 0, valid.shape[1] - 1)
                    iy = np.clip(np.rint(px[..., 1]).astype(int), 0, valid.shape[0] - 1)
                    ok &= np.all(valid[iy, ix], axis=0)
                a, b = _longest_run(ok)
                if b - a < 8:
                    continue
                lines.append(
                    StivLine(
                        i,
                        c + 0.5 * (s[a] + s[b - 1]) * e,
                        e,
                        float(s[b - 1] - s[a]),
                        ds,
                        px[:, a:b].astype(np.float32),
                        float(ang),
                    )
                )
    return lines


def _longest_run(ok: np.ndarray) -> tuple[int, int]:
    """[a, b) of the longest run of True in ``ok`` (the first of equal ones; (0, 0) when none)."""
    d = np.diff(np.r_[0, np.asarray(ok, np.int8), 0])
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if not len(starts):
        return 0, 0
    k = int(np.argmax(ends - starts))
    return int(starts[k]), int(ends[k])


def _mean_f16(rows: np.ndarray) -> np.ndarray:
    """``rows.mean(axis=0).astype(np.float16)`` for a (k, n) float32 array, the same numbers (NumPy sums the rows
    of an axis-0 mean in order, then divides in float32; OpenCV's conversion to float16 rounds to nearest even, as
    NumPy's), in a fifth of the time: NumPy's float16 conversion is done in software, element by element."""
    acc = rows[0].copy()
    for r in rows[1:]:
        cv2.add(acc, r, dst=acc)
    cv2.divide(acc, float(len(rows)), dst=acc)  # type: ignore[call-overload, unused-ignore]
    return cv2.multiply(acc, 1.0, dtype=cv2.CV_16F).ravel()


class StiAccumulator:
    """Builds the space-time images of ``lines`` one frame at a time (only the samples are kept, as
    float16: frames x samples x 2 bytes, never the frames)."""

    def __init__(self, lines: list[StivLine]):
        self.lines = lines
        self.bounds = np.cumsum([0] + [ln.pts_px.shape[1] for ln in lines])
        width = {ln.pts_px.shape[0] for ln in lines}
        if len(width) > 1:
            raise ParameterError("stiv: all search lines must have the same width")
        pts = np.concatenate([ln.pts_px for ln in lines], axis=1) if lines else np.zeros((1, 0, 2), np.float32)
        self.width, self.n = pts.shape[0], pts.shape[1]
        # remap wants maps narrower than 32767: fold the samples into rows of 4096 (padded with the first point)
        flat = pts.reshape(-1, 2)
        rows = -(-len(flat) // 4096) if len(flat) else 1
        padded = np.empty((rows * 4096, 2), np.float32)
        padded[:] = flat[0] if len(flat) else 0.0
        padded[: len(flat)] = flat
        self._map = (
            np.ascontiguousarray(padded[:, 0].reshape(rows, 4096)),
            np.ascontiguousarray(padded[:, 1].reshape(rows, 4096)),
        )
        self._crop: tuple | None = None  # (rows slice, cols slice, map_x, map_y, frame shape) of the last frame size
        self.rows: list[np.ndarray] = []
        self.times: list[float] = []

    def _cropped(self, shape: tuple[int, int]) -> tuple:
        """The frame's box that the bilinear samples read, and the maps shifted into it. Points outside the frame
        keep the box at the frame's edge, so BORDER_REPLICATE reads as on the whole frame: same samples."""
        if self._crop is None or self._crop[4] != shape:
            mx, my = self._map
            h, w = shape
            x0 = int(np.clip(np.floor(mx.min()) - 1, 0, w - 1))
            y0 = int(np.clip(np.floor(my.min()) - 1, 0, h - 1))
            x1 = int(np.clip(np.floor(mx.max()) + 3, x0 + 1, w))
            y1 = int(np.clip(np.floor(my.max()) + 3, y0 + 1, h))
            self._crop = (slice(y0, y1), slice(x0, x1), mx - np.float32(x0), my - np.float32(y0), shape)
        return self._crop

    def box(self, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
        """(x0, y0, x1, y1) px: the box of a frame of ``shape`` that :meth:`add` reads; None without lines."""
        if not len(self.lines):
            return None
        rs, cs = self._cropped(shape)[:2]
        return cs.start, rs.start, cs.stop, rs.stop

    def add(self, t_s: float, frame: np.ndarray) -> None:
        """Sample one working frame (gray, any dtype) taken at ``t_s`` seconds. Only the lines' box is read (and
        converted to float32)."""
        if not len(self.lines):
            return
        rs, cs, map_x, map_y, _ = self._cropped(frame.shape[:2])
        img = frame[rs, cs].astype(np.float32)
        row = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        row = row.ravel()[: self.width * self.n].reshape(self.width, self.n)
        self.rows.append(_mean_f16(row))
        self.times.append(float(t_s))

    def tap(self, frames):
        """Pass a (t_s, frame) stream through unchanged, sampling every frame on the way."""
        for t, img in frames:
            self.add(t, img)
            yield t, img

    def sti(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(STI (T, n) of line ``k``, times (T,) s)."""
        a, b = self.bounds[k], self.bounds[k + 1]
        return np.stack([r[a:b] for r in self.rows]).astype(np.float32), np.asarray(self.times)


# ---------------------------------------------------------------------------------------------
# one space-time image -> one velocity


def uniform_time(sti: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, float]:
    """Resample the rows of ``sti`` onto a uniform time grid (step = the median frame interval, s),
    linearly between the frames' own timestamps. Returns (STI, dt_s)."""
    t = np.asarray(t_s, float)
    dts = np.diff(t)
    if len(dts) == 0 or not np.all(dts > 0):
        raise ParameterError("frames: STIV needs at least 2 frames with increasing timestamps")
    dt = float(np.median(dts))
    if np.allclose(dts, dt, rtol=1e-3, atol=1e-6):
        return np.asarray(sti, np.float32), dt
    grid = t[0] + dt * np.arange(int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1)
    j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 2)
    w = ((grid - t[j]) / (t[j + 1] - t[j]))[:, None]
    return ((1 - w) * sti[j] + w * sti[j + 1]).astype(np.float32), dt


HIGHPASS_S = 1.0  # temporal high-pass of the STI columns: running mean over this many seconds removed


def _prepare(sti: np.ndarray, rows: int | None = None) -> np.ndarray:
    """Remove what draws no streak: each column's running mean over ``rows`` rows (all rows when None:
    static texture; a window: also slow changes in place such as glints switching and ripple fields
    fading), then each row's mean (global brightness changes)."""
    a = np.asarray(sti, np.float64)
    if rows is None or rows >= a.shape[0]:
        a = a - a.mean(axis=0, keepdims=True)
    else:
        a = a - uniform_filter1d(a, size=max(rows, 2), axis=0, mode="nearest")
    return a - a.mean(axis=1, keepdims=True)


def _autocorrelation(sti: np.ndarray, K: int, half: int) -> np.ndarray:
    """Sums of products of ``sti`` (T, S) with itself shifted by 0..K rows and -half..half samples: (K + 1,
    2 * half + 1), float64, column ``half`` the zero shift. By FFT (float32), zero-padded to what keeps these
    lags free of the circular wrap, T + K rows and S + half columns (padding to 2T x 2S computed lags nobody
    reads: 1.5 times the time on 1080p's 30 s STIs, the same lags to float32's rounding)."""
    T, S = sti.shape
    shape = (sfft.next_fast_len(T + K, real=True), sfft.next_fast_len(S + half, real=True))
    F = sfft.rfft2(np.asarray(sti, np.float32), s=shape)
    R = sfft.irfft2(F * np.conj(F), s=shape)
    return np.concatenate([R[: K + 1, -half:], R[: K + 1, : half + 1]], axis=1).astype(np.float64)


def orientation_fft(sti: np.ndarray, max_lag: int | None = None, n_angles: int = 360) -> tuple[float, float]:
    """Streak slope of a uniform-time STI by its 2-D autocorrelation, in samples per row.

    Parameters
    ----------
    sti : (T, S) prepared STI (zero-mean columns).
    max_lag : most row lags integrated (default T // 2).
    n_angles : coarse angle grid over (-90°, 90°); the best cell is searched again 20x finer, then
        refined by a parabola.

    Returns
    -------
    (slope samples/row, confidence 0..1): the mean normalised autocorrelation along the best line.
    """
    T, S = sti.shape
    K = max(1, min(max_lag or T // 2, T // 2))
    half = S // 2
    R = _autocorrelation(sti, K, half)
    # unbiased by the overlap count
    overlap = (T - np.arange(K + 1))[:, None] * (S - np.abs(np.arange(-half, half + 1)))[None, :]
    R = R / overlap
    if not R[0, half] > 0:
        return float("nan"), 0.0
    R /= R[0, half]
    k = np.arange(1, K + 1)

    def score(theta: np.ndarray) -> np.ndarray:
        sig = np.tan(theta)[:, None] * k[None, :] + half  # column index of the line at lag k
        inside = (sig >= 0) & (sig <= 2 * half)
        s0 = np.clip(np.floor(sig).astype(int), 0, 2 * half - 1)
        f = np.clip(sig - s0, 0, 1)
        rows = np.broadcast_to(k, sig.shape)
        val = (1 - f) * R[rows, s0] + f * R[rows, s0 + 1]
        cnt = inside.sum(axis=1)
        return np.where(cnt >= 3, np.where(inside, val, 0).sum(axis=1) / np.maximum(cnt, 1), -np.inf)

    step = np.pi / n_angles
    coarse = -np.pi / 2 + step * np.arange(1, n_angles)
    m = int(np.argmax(score(coarse)))
    fine = coarse[m] + np.linspace(-step, step, 41)[1:-1]
    fine = fine[np.abs(fine) < np.pi / 2]
    sc = score(fine)
    m = int(np.argmax(sc))
    if not np.isfinite(sc[m]):
        return float("nan"), 0.0
    th = fine[m]
    if 0 < m < len(fine) - 1 and np.all(np.isfinite(sc[m - 1 : m + 2])):
        y0, y1, y2 = sc[m - 1 : m + 2]
        den = y0 - 2 * y1 + y2
        if den < 0:
            th += 0.5 * (y0 - y2) / den * (fine[1] - fine[0])
    return float(np.tan(th)), float(np.clip(sc[m], 0.0, 1.0))


def orientation_tensor(sti: np.ndarray, sigma: float = 1.0) -> tuple[float, float]:
    """Streak slope of a uniform-time STI by the structure tensor (samples per row) and its coherence."""
    a = cv2.GaussianBlur(np.asarray(sti, np.float32), (0, 0), sigma)
    gs = cv2.Scharr(a, cv2.CV_64F, 1, 0)
    gt = cv2.Scharr(a, cv2.CV_64F, 0, 1)
    jss, jtt, jst = float(np.sum(gs * gs)), float(np.sum(gt * gt)), float(np.sum(gs * gt))
    tr = jss + jtt
    if not tr > 0:
        return float("nan"), 0.0
    phi = 0.5 * np.arctan2(2 * jst, jss - jtt)  # direction of the dominant gradient, (s, t) axes
    coh = float(np.hypot(jss - jtt, 2 * jst) / tr)
    c = np.cos(phi)
    if abs(c) < 1e-9:
        return float("nan"), coh
    return float(-np.tan(phi)), coh


def sti_velocity(
    sti: np.ndarray, t_s: np.ndarray, ds_m: float, method: str = "fft", max_lag_s: float | None = None
) -> tuple[float, float]:
    """Velocity along a line (m/s, positive in the line's direction) and its confidence (0..1).

    Parameters
    ----------
    sti : (T, S) samples along the line at successive frames.
    t_s : (T,) frame times from the container (s).
    ds_m : sample spacing along the line (m).
    method : "fft" or "tensor" (see the module docstring).
    max_lag_s : fft: longest time lag integrated (s); None = half the clip.
    """
    if method not in METHODS:
        raise ParameterError(f"stiv.method: {method!r} is not one of {', '.join(METHODS)}")
    u, dt = uniform_time(sti, t_s)
    if u.shape[0] < 4 or u.shape[1] < 8:
        return float("nan"), 0.0
    a = _prepare(u, int(round(HIGHPASS_S / dt)))
    if method == "fft":
        lag = None if max_lag_s is None else max(1, int(round(max_lag_s / dt)))
        p, conf = orientation_fft(a, lag)
    else:
        p, conf = orientation_tensor(a)
    if not np.isfinite(p):
        return float("nan"), 0.0
    return p * ds_m / dt, conf


# ---------------------------------------------------------------------------------------------
# all lines -> subsections


@dataclass
class StivResult:
    """Per-line and per-subsection STIV velocities (m/s) with confidences (0..1).

    ``line_velocity_ms`` is signed along each line; ``velocity_ms`` / ``confidence`` per subsection are
    the downstream-normal components of the geometry passed to :func:`subsection_velocity` (NaN where no
    line passed ``min_confidence``); ``angle_deg`` the chosen line turn per subsection.
    """

    line_velocity_ms: np.ndarray
    line_confidence: np.ndarray
    velocity_ms: np.ndarray
    confidence: np.ndarray
    angle_deg: np.ndarray
    method: str
    n_lines: int
    n_frames: int
    warnings: list[str] = field(default_factory=list)


def select_lines(
    lines: list[StivLine], n_sub: int, flow_dir: np.ndarray | None = None, reversed_order: bool = False
) -> np.ndarray:
    """Which lines to analyse (bool per line): in each subsection the angle nearest the flow direction
    ``flow_dir`` ((n_sub, 2) world unit vectors of the geometry's subsections, NaN rows allowed), or
    every angle where the direction is unknown (the most confident is chosen afterwards)."""
    use = np.ones(len(lines), bool)
    if flow_dir is None:
        return use
    for i in range(n_sub):
        src = n_sub - 1 - i if reversed_order else i
        if not np.all(np.isfinite(flow_dir[i])):
            continue
        idx = [k for k, ln in enumerate(lines) if ln.sub == src]
        if not idx:
            continue
        dots = np.array([abs(np.dot(lines[k].direction, flow_dir[i])) for k in idx])
        best = lines[idx[int(np.argmax(dots))]].angle_deg
        for k in idx:
            use[k] = lines[k].angle_deg == best
    return use


def guide_directions(
    flow_dir: np.ndarray, normal: np.ndarray, weight: np.ndarray, min_weight: float = 0.5, max_dev_deg: float = 15.0
) -> np.ndarray:
    """Flow directions to orient the lines by, per subsection, from a noisy field (e.g. the PIV's).

    The section's direction is the median angle (from ``normal``, folded to ±90°: a line has no sign) of
    the subsections whose ``weight`` (0..1, e.g. PIV's valid-pair fraction) reaches ``min_weight``; a
    subsection keeps its own direction when it is that trustworthy and within ``max_dev_deg`` of the
    section's, else takes the section's. All NaN when no subsection is trustworthy.

    Parameters
    ----------
    flow_dir : (n, 2) world unit vectors (NaN rows allowed). normal : (2,) section normal (world).
    weight : (n,) confidence of each direction.
    """
    f = np.asarray(flow_dir, float)
    n = np.asarray(normal, float)
    phi = np.degrees(np.arctan2(n[0] * f[:, 1] - n[1] * f[:, 0], f @ n))
    phi = (phi + 90.0) % 180.0 - 90.0
    good = np.isfinite(phi) & (np.asarray(weight, float) >= min_weight)
    out = np.full_like(f, np.nan)
    if not good.any():
        return out
    ref = float(np.median(phi[good]))
    use = np.where(good & (np.abs(phi - ref) <= max_dev_deg), phi, ref)
    for i, a in enumerate(use):
        out[i] = _rot(n, a)
    return out


def line_velocities(
    acc: StiAccumulator, method: str = "fft", max_lag_s: float | None = None, only: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (m/s along each line) and confidence of the lines of ``acc`` (those where ``only`` is
    True; the others get NaN and 0)."""
    v = np.full(len(acc.lines), np.nan)
    c = np.zeros(len(acc.lines))
    if len(acc.rows) < 4:
        return v, c
    todo = [k for k in range(len(acc.lines)) if only is None or only[k]]

    def lines(lo: int, hi: int) -> None:  # each line on its own: the same numbers in any order
        for k in todo[lo:hi]:
            sti, t = acc.sti(k)
            v[k], c[k] = sti_velocity(sti, t, acc.lines[k].ds_m, method, max_lag_s)

    # on the engine's threads (the FFTs, sorts and filters release the GIL): a long clip's lines at the run's end
    piv_engine.chunked(len(todo), max(1, -(-len(todo) // 2)), lines)
    return v, c


# ---------------------------------------------------------------------------------------------
# wind ripples: the velocity from the waves' dispersion

G_MS2 = 9.81  # gravity (m/s²)
SIGMA_RHO = 0.074 / 1000.0  # surface tension over density of clean water (m³/s²)
#: longest wave fitted (m): in water deeper than half of it (0.25 m) a wave is a deep-water wave, tanh(kh) > 0.996
WAVE_LAMBDA_MAX_M = 0.5
WAVE_BAND = 1  # spectral cells each side of a model's curve counted as on it (the spectrum's own resolution)
RIPPLES_LEAD_SHARE = 0.5  # a clip is led by ripples where they lead on more than this share of the lines fitted


def wave_omega(k: np.ndarray) -> np.ndarray:
    """Angular frequency (rad/s) of deep-water gravity-capillary waves of wavenumber ``k`` (rad/m) in still
    water: ω² = g|k| + (σ/ρ)|k|³."""
    k = np.abs(np.asarray(k, float))
    return np.sqrt(G_MS2 * k + SIGMA_RHO * k**3)


@dataclass
class WaveFit:
    """One STI's spectrum against three models of what draws it (the shares of its energy in each model's cells at
    ``velocity_ms``, the flicker's at its best frequency, net of what a flat spectrum puts there, 0..1):

    * ``line``: a pattern carried by the flow, energy on ω = -kU (tracers, foam, turbulence);
    * ``waves``: waves on the water carried by it, on ω = -kU ± ω_w(k) (wind ripples, read at the joint U);
    * ``flicker``: brightness that changes in place at one frequency whatever the wavenumber (glints, rain, a
      pumping exposure), on ω = ±ω0.

    ``velocity_ms`` is the U (m/s along the line) at which the carried pattern and the waves together explain the
    most energy; ``waves_lead`` says that there the waves carry more of it than the pattern, and explain more than
    any flicker and more than the best carried pattern alone (on a 1.5 s clip the frequency cells are coarse, and a
    wave curve followed a tracer line over a wide band of wavenumbers: far_bank read +24 %)."""

    velocity_ms: float
    line: float
    waves: float
    flicker: float
    waves_lead: bool
    joint: float  # the share the pattern and the waves explain together at ``velocity_ms``, net (0..1)


def _band_sums(P: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """For the columns of ``P`` (T, n): the energy within WAVE_BAND cells of row ``j`` (.., n) of each, rows
    wrapped (aliasing), from one cumulative sum."""
    T, n = P.shape
    b = WAVE_BAND
    ext = np.concatenate([P[T - b :], P, P[:b]], axis=0)
    C = np.concatenate([np.zeros((1, n)), np.cumsum(ext, axis=0)], axis=0)
    cols = np.arange(n)

    def band(j: np.ndarray) -> np.ndarray:
        jj = np.mod(j, T)
        return C[jj + 2 * b + 1, cols] - C[jj, cols]

    return band


def wave_fit(sti: np.ndarray, dt: float, ds_m: float) -> WaveFit | None:
    """The waves' dispersion against a carried pattern on one prepared, uniform-time STI (T, S) with rows ``dt``
    s and samples ``ds_m`` m apart; None where the line resolves fewer than 2 wavenumbers between
    2π/WAVE_LAMBDA_MAX_M and 0.8 of Nyquist, or the STI is flat.

    Wind ripples travel on the water at their own phase speed c(k) = ω_w(k)/k (0.23 m/s and up, 0.36 m/s at 8 cm,
    0.88 m/s at 50 cm): a line model reads them as a pattern at U - c, too slow, and since c changes with k their
    energy lies on a curve, not a line. Both models are fitted over U on the Hann-windowed power spectrum (a grid
    4 cells of the finest velocity resolution apart, then that resolution around the best); the share of each is
    counted in the cells within WAVE_BAND of its curves, net of the share a flat spectrum would put there."""
    T, S = sti.shape
    # k >= 0 only: a real STI's spectrum is symmetric, P(-k, -ω) = P(k, ω), and so is every model's curve
    P = np.abs(sfft.rfft2(sti * (np.hanning(T)[:, None] * np.hanning(S)[None, :]))) ** 2
    k = sfft.rfftfreq(S, ds_m) * 2 * np.pi
    cols = np.nonzero((k >= 2 * np.pi / WAVE_LAMBDA_MAX_M) & (k <= 0.8 * np.pi / ds_m))[0]
    if len(cols) < 2 or T < 8:
        return None
    P, k = P[:, cols], k[cols]
    tot = float(P.sum())
    if not tot > 0:
        return None
    band = _band_sums(P)
    dw = 2 * np.pi / (T * dt)
    om = wave_omega(k)

    def net(share, n_curves: int):
        f = min(1.0, n_curves * (2 * WAVE_BAND + 1) / T)
        return (share - f) / (1 - f) if f < 1 else share * 0.0

    def shares(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # (line, waves) at each U
        w = -k[None, :] * U[:, None]
        line = band(np.rint(w / dw).astype(int)).sum(axis=1) / tot
        waves = (band(np.rint((w - om) / dw).astype(int)) + band(np.rint((w + om) / dw).astype(int))).sum(axis=1)
        return line, waves / tot

    step = max(dw / (2 * float(k.max())), 0.005)
    u_max = min(10.0, np.pi / dt / float(k.min()))  # the fastest pattern whose slowest wave is not aliased
    coarse = np.arange(-u_max, u_max + step, 4 * step)
    line, waves = shares(coarse)
    line_best = float(np.max(net(line, 1)))  # the best carried pattern alone (the coarse grid's)
    m = int(np.argmax(line + waves))
    U = coarse[m] + step * np.arange(-8, 9)
    line, waves = shares(U)
    joint = line + waves
    m = int(np.argmax(joint))
    u = float(U[m])
    if 0 < m < len(U) - 1:
        y0, y1, y2 = joint[m - 1 : m + 2]
        den = y0 - 2 * y1 + y2
        if den < 0:
            u += float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) * step
    w0 = np.arange(T // 2 + 1)[:, None]  # every frequency cell, the same in every column
    flicker = float(np.max(net((band(w0) + band(-w0)).sum(axis=1) / tot, 2)))
    nw = float(net(waves[m], 2))
    return WaveFit(
        u,
        float(net(line[m], 1)),
        nw,
        flicker,
        bool(waves[m] > line[m] and nw > flicker and nw > line_best),
        float(np.clip(net(joint[m], 3), 0.0, 1.0)),
    )


@dataclass
class Ripples:
    """The clip's lines against wind ripples (:func:`wave_fit` on each line analysed). ``dominated``: the waves lead
    on more than :data:`RIPPLES_LEAD_SHARE` of the lines fitted; then ``velocity_ms`` (per line, m/s, NaN where not
    fitted) replaces the lines' velocities, with ``confidence`` (the share of the line's spectrum the waves and the
    carried pattern explain together, net of a flat spectrum's, 0..1)."""

    velocity_ms: np.ndarray
    confidence: np.ndarray
    n_fitted: int
    n_waves: int

    @property
    def dominated(self) -> bool:
        return self.n_fitted > 0 and self.n_waves > RIPPLES_LEAD_SHARE * self.n_fitted

    def to_dict(self) -> dict:
        return {"lines_fitted": self.n_fitted, "lines_led_by_waves": self.n_waves, "dominated": self.dominated}


def ripples(acc: StiAccumulator, only: np.ndarray | None = None) -> Ripples:
    """:func:`wave_fit` on the lines of ``acc`` (those where ``only`` is True), on the engine's threads."""
    u = np.full(len(acc.lines), np.nan)
    conf = np.zeros(len(acc.lines))
    lead = np.zeros(len(acc.lines), bool)
    fitted = np.zeros(len(acc.lines), bool)
    if len(acc.rows) < 8:
        return Ripples(u, conf, 0, 0)
    todo = [k for k in range(len(acc.lines)) if only is None or only[k]]

    def lines(lo: int, hi: int) -> None:
        for k in todo[lo:hi]:
            sti, t = acc.sti(k)
            a, dt = uniform_time(sti, t)
            fit = wave_fit(_prepare(a, int(round(HIGHPASS_S / dt))), dt, acc.lines[k].ds_m)
            if fit is not None:
                u[k], conf[k], lead[k], fitted[k] = fit.velocity_ms, fit.joint, fit.waves_lead, True

    piv_engine.chunked(len(todo), max(1, -(-len(todo) // 2)), lines)
    return Ripples(u, conf, int(fitted.sum()), int(lead.sum()))


def along_fastest(
    lines: list[StivLine], v_line: np.ndarray, n_sub: int, reversed_order: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Per subsection, the lines of the angle along which the median velocity (m/s, downstream positive) is the
    fastest: a flow at ``phi`` reads ``U cos(angle - phi)`` along a line, so the fastest angle is the flow's.
    For a clip led by ripples, whose pattern turns PIV's flow directions too. Returns (which lines, bool per line;
    the flow direction per subsection of the geometry, (n_sub, 2) world unit vectors, NaN rows where no line
    measured)."""
    use = np.zeros(len(lines), bool)
    flow = np.full((n_sub, 2), np.nan)
    subs = np.array([ln.sub for ln in lines], int)
    angles = np.array([ln.angle_deg for ln in lines])
    v = np.asarray(v_line, float)
    for i in range(n_sub):
        src = n_sub - 1 - i if reversed_order else i
        cand = [a for a in np.unique(angles[subs == src]) if np.isfinite(v[(subs == src) & (angles == a)]).any()]
        if not cand:
            continue
        best = max(cand, key=lambda a: float(np.nanmedian(v[(subs == src) & (angles == a)])))
        pick = (subs == src) & (angles == best)
        use |= pick
        flow[i] = lines[int(np.nonzero(pick)[0][0])].direction
    return use, flow


def subsection_velocity(
    lines: list[StivLine],
    v_line: np.ndarray,
    c_line: np.ndarray,
    n_sub: int,
    normal: np.ndarray,
    reversed_order: bool = False,
    flow_dir: np.ndarray | None = None,
    min_confidence: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Downstream-normal velocity (m/s), confidence and flow angle (deg from the lines' normal) per subsection.

    A tracer crossing a line obliquely draws a short streak, so each subsection uses the lines of one
    angle, the one nearest the flow: the flow direction is ``flow_dir`` ((n_sub, 2) world unit vectors,
    e.g. the PIV mean direction; NaN rows allowed) or, without it, the vertex of a parabola through the
    mean line confidence over the angles (streaks are longest, so confidence highest, along the flow).
    A line along ``e`` measuring ``v`` along a flow ``f`` gives the normal component
    ``v / (e · f) * (f · normal)``. The lines that pass ``min_confidence`` are averaged (they are spread
    evenly across the subsection); the confidence is their mean. ``normal`` is the geometry's normal;
    ``reversed_order`` when its subsections run the other way from the lines' (P1/P2 swapped after the
    lines were built).
    """
    vel = np.full(n_sub, np.nan)
    conf = np.zeros(n_sub)
    ang = np.full(n_sub, np.nan)
    subs = np.array([ln.sub for ln in lines], int)
    angles = np.array([ln.angle_deg for ln in lines])
    for i in range(n_sub):
        src = n_sub - 1 - i if reversed_order else i
        sel = np.nonzero((subs == src) & np.isfinite(v_line) & (c_line >= min_confidence))[0]
        if not len(sel):
            continue
        cand = np.unique(angles[sel])
        mc = np.array([c_line[sel][angles[sel] == a].mean() for a in cand])
        e_of = {a: lines[sel[angles[sel] == a][0]].direction for a in cand}
        if flow_dir is not None and np.all(np.isfinite(flow_dir[i])):
            best = cand[int(np.argmax([abs(np.dot(e_of[a], flow_dir[i])) for a in cand]))]
            f = np.asarray(flow_dir[i], float) * np.sign(np.dot(e_of[best], flow_dir[i]) or 1.0)
        else:
            k = int(np.argmax(mc))
            best, phi = cand[k], cand[k]
            if 0 < k < len(cand) - 1 and np.allclose(np.diff(cand[k - 1 : k + 2]), cand[k] - cand[k - 1]):
                den = mc[k - 1] - 2 * mc[k] + mc[k + 1]
                if den < 0:
                    phi += float(np.clip(0.5 * (mc[k - 1] - mc[k + 1]) / den, -0.5, 0.5)) * (cand[k] - cand[k - 1])
            f = _rot(e_of[best], phi - best)
        e = e_of[best]
        use = sel[angles[sel] == best]
        # lines spread evenly: their plain mean is the subsection's
        vel[i] = float(np.mean(v_line[use]) / max(np.dot(e, f), 0.5) * np.dot(f, normal))
        conf[i] = float(np.mean(c_line[use]))
        ang[i] = float(best + np.degrees(np.arctan2(e[0] * f[1] - e[1] * f[0], np.dot(e, f))))
    return vel, conf, ang


# ---------------------------------------------------------------------------------------------
# PIV against STIV

DISAGREE_REL = 0.15  # a subsection disagrees when |v_stiv - v_piv| exceeds this share of its reference speed
DISAGREE_Q = 0.05  # ... the discharges when they differ by more than this share (the 5 % accuracy aimed at)
DISAGREE_SHARE = 0.2  # ... or when disagreeing subsections carry more than this share of the discharge
MIN_COMPARED = 3  # fewer subsections measured by both cannot show that the two agree (nor bound an under-read)


def disagreement(
    v_piv: np.ndarray, v_stiv: np.ndarray, q_weight: np.ndarray, rel_threshold: float = DISAGREE_REL
) -> dict:
    """Relative PIV/STIV disagreement on the subsections where both measured (NaN-free, JSON-ready).

    Parameters
    ----------
    v_piv, v_stiv : (n,) downstream-normal surface velocities (m/s), NaN where not measured.
    q_weight : (n,) alpha * area of each subsection (m²): turns a velocity into a discharge.
    rel_threshold : a subsection disagrees when |v_stiv - v_piv| > this times max(|v_piv|, 10 % of the
        section's fastest PIV velocity).

    Returns
    -------
    dict: ``discharge_relative`` (Q_stiv - Q_piv) / Q_piv over the compared subsections; ``subsections_relative``
    per subsection (None where not compared); ``subsections_over_threshold`` (1-based); ``share_of_discharge``
    the PIV discharge share of those; ``threshold``; ``n_compared``.
    """
    v_piv, v_stiv, q_weight = (np.asarray(a, float) for a in (v_piv, v_stiv, q_weight))
    both = np.isfinite(v_piv) & np.isfinite(v_stiv)
    top = float(np.max(np.abs(v_piv[np.isfinite(v_piv)]))) if np.any(np.isfinite(v_piv)) else 0.0
    ref = np.maximum(np.abs(np.nan_to_num(v_piv)), 0.1 * top)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(both & (ref > 0), (v_stiv - v_piv) / ref, np.nan)
    qp_sub = np.where(both, q_weight * v_piv, 0.0)
    qp = float(np.sum(qp_sub))
    qs = float(np.sum(np.where(both, q_weight * v_stiv, 0.0)))
    bad = np.nonzero(np.abs(np.nan_to_num(rel)) > rel_threshold)[0]
    return {
        "discharge_relative": (qs - qp) / qp if qp != 0 and both.any() else None,
        "subsections_relative": [None if not np.isfinite(r) else float(r) for r in rel],
        "subsections_over_threshold": [int(i) + 1 for i in bad],
        "share_of_discharge": float(np.sum(np.abs(qp_sub[bad])) / np.sum(np.abs(qp_sub))) if qp != 0 else 0.0,
        "threshold": rel_threshold,
        "n_compared": int(both.sum()),
    }


def agree(dis: dict) -> bool:
    """PIV and STIV agree: :data:`MIN_COMPARED` subsections or more measured by both, and no
    :func:`disagreement_reason`."""
    return dis.get("n_compared", 0) >= MIN_COMPARED and disagreement_reason(dis) is None


def disagreement_reason(
    dis: dict, q_threshold: float = DISAGREE_Q, share_threshold: float = DISAGREE_SHARE
) -> dict | None:
    """A "doubtful" reason of the quality verdict when PIV and STIV disagree (see :func:`disagreement`), as
    the fields of a quality reason (code, severity, message, value, threshold); None when they agree.
    Two estimators that disagree say the velocity is uncertain, not which one is right: never "unusable"."""
    dq_rel = dis.get("discharge_relative")
    share = dis.get("share_of_discharge", 0.0)
    bad = dis.get("subsections_over_threshold", [])
    q_bad = dq_rel is not None and abs(dq_rel) > q_threshold
    if not (q_bad or (bad and share > share_threshold)):
        return None
    rel = [abs(dis["subsections_relative"][i - 1]) for i in bad]
    where = (
        (
            f" on subsection(s) {', '.join(map(str, bad[:8]))}{' ...' if len(bad) > 8 else ''} (up to "
            f"{100 * max(rel):.0f} %, {100 * share:.0f} % of the discharge)"
        )
        if bad
        else ""
    )
    qtxt = f"; the discharge by STIV differs by {100 * dq_rel:+.1f} %" if dq_rel is not None else ""
    return {
        "code": "piv_stiv_disagree",
        "severity": "doubtful",
        "message": f"PIV and STIV disagree by more than {100 * dis['threshold']:.0f} %{where}{qtxt}: sparse or "
        "patchy seeding, stationary patterns or ripples mislead one of them; compare the velocities in "
        "subsections.csv (stiv_velocity_ms) and consider section.velocity_source",
        "value": float(abs(dq_rel)) if q_bad and dq_rel is not None else float(share),
        "threshold": q_threshold if q_bad else share_threshold,
    }


def implied_underread(dis: dict | None, z: float = 2.0, min_compared: int = MIN_COMPARED) -> dict | None:
    """The under-read of the PIV velocities that the independent STIV supports, at about 95 % (one-sided).

    ``dis`` is :func:`disagreement`'s block. Where STIV reads faster than PIV by ``d`` (its
    ``discharge_relative``), the PIV may under-read by the fraction ``d / (1 + d)`` (``Q / (1 - u)`` then
    equals STIV's discharge). ``d`` is uncertain itself: its standard error is the spread of the per-subsection
    differences over ``sqrt(n_eff)`` (:func:`_evidence`). The bound is ``d + z * se``; where STIV reads slower
    than PIV by more than its noise, it supports no under-read (0).

    Returns ``{"fraction", "stiv_relative", "se", "n_compared", "n_eff"}`` (fractions of Q), or None where
    :func:`_evidence` finds none: the run then keeps the project's prior, the keys
    ``uncertainty.underread_doubtful`` / ``underread_unusable``.
    """
    ev = _evidence(dis, min_compared)
    if ev is None:
        return None
    d, rel, n_eff = ev
    se = float(np.std(rel, ddof=1) / np.sqrt(n_eff))
    hi = d + z * se
    return _implied(hi / (1.0 + hi) if hi > 0 else 0.0, d, se, rel, n_eff)


def implied_overread(dis: dict | None, z: float = 2.0, min_compared: int = MIN_COMPARED) -> dict | None:
    """The over-read of the PIV velocities that the independent STIV supports, at about 95 % (one-sided): the
    mirror of :func:`implied_underread`, with STIV's own failures kept out. Where STIV reads slower than PIV by
    ``-m``, PIV may over-read by the fraction ``-m`` (``Q (1 - o)`` then equals STIV's), bounded at
    ``-(m - z * se)``; where STIV reads faster by more than its noise, it supports no over-read (0).

    ``m`` is the median of the per-subsection differences, not the discharge's: STIV fails in a subsection by
    reading near zero or upstream (ripples and waves against the flow: -88 % to -685 % of PIV in single
    subsections of drawn scenes whose PIV was right), which only ever reads as an over-read of PIV, so a few such
    subsections must not make one. Its standard error is the median's, ``1.2533 * 1.4826 * MAD / sqrt(n_eff)``
    (``n_eff`` as in :func:`_evidence`). Returns the keys of :func:`implied_underread` (``stiv_relative`` the
    median), or None where :func:`_evidence` finds none: nothing else bounds an over-read."""
    ev = _evidence(dis, min_compared)
    if ev is None:
        return None
    _, rel, n_eff = ev
    med = float(np.median(rel))
    se = float(1.2533 * 1.4826 * np.median(np.abs(rel - med)) / np.sqrt(n_eff))
    lo = med - z * se
    return _implied(-lo if lo < 0 else 0.0, med, se, rel, n_eff)


def _implied(fraction: float, relative: float, se: float, rel: np.ndarray, n_eff: float) -> dict:
    """The block :func:`implied_underread` and :func:`implied_overread` return."""
    return {"fraction": float(fraction), "stiv_relative": relative, "se": se, "n_compared": len(rel), "n_eff": n_eff}


def _evidence(dis: dict | None, min_compared: int = MIN_COMPARED) -> tuple[float, np.ndarray, float] | None:
    """What STIV's disagreement with PIV says: (``d``, the per-subsection differences, ``n_eff``).

    ``d`` is :func:`disagreement`'s ``discharge_relative`` (STIV's discharge over PIV's, minus 1, over the
    subsections both measured); the differences are its finite ``subsections_relative``; ``n_eff = n (1 - r) /
    (1 + r)`` for the lag-1 autocorrelation ``r >= 0`` of those differences along the section (neighbouring
    subsections share texture, lines and errors: AR(1) effective sample size).

    None when STIV compared fewer than ``min_compared`` subsections, or where its discharge over them is zero or
    upstream (``d <= -1``) while PIV's goes downstream: STIV then measured something else than the river (ripples
    or waves travelling against it read -325 % of PIV's Q on a drawn scene, and bounded the under-read to 0 where
    PIV read -66 %).
    """
    if not dis or dis.get("discharge_relative") is None:
        return None
    rel = np.asarray([r for r in dis.get("subsections_relative") or [] if r is not None], float)
    rel = rel[np.isfinite(rel)]
    n = len(rel)
    d = float(dis["discharge_relative"])
    if n < max(min_compared, 2) or not np.isfinite(d) or d <= -1.0:
        return None
    r = 0.0
    if n >= 3:
        a, b = rel[:-1] - rel.mean(), rel[1:] - rel.mean()
        den = float(np.sum((rel - rel.mean()) ** 2))
        r = float(np.clip(np.sum(a * b) / den, 0.0, 0.95)) if den > 0 else 0.0
    return d, rel, float(np.clip(n * (1.0 - r) / (1.0 + r), 1.0, n))
