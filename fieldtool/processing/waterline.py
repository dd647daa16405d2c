"""Automatic water line: the water edges along a search line across the river, found in the video.

Flowing water changes from frame to frame (tracers, ripples, glints); banks do not. Along a search line
that crosses the river from bank to bank, the temporal standard deviation of the grey levels (averaged
over a thin band across the line) is high over the water and low over the banks. The water edges are
where that activity falls from the water's level to the bank's, searched outwards from the middle of
the line (see :func:`find_edges`); their sub-pixel position comes from linear interpolation, and their
1-sigma from the steepness of the transition. With the ortho mapping and the cross-section, the two
edges give the wetted width and so the water level (as the thesis' image method, 5.3, without clicks).

Image space: working-image pixels (undistorted), x right, y down. Intensities 0-255.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from ..errors import GeometryError, ParameterError


def extend_line(p0, p1, factor: float, shape: tuple[int, int]) -> np.ndarray:
    """The segment p0-p1 (px) lengthened by ``factor`` of its length at both ends and clipped to a frame
    of ``shape`` (H, W): a default search line from the picked section points."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    a, b = p0 - factor * d, p1 + factor * d
    h, w = shape
    lo, hi = np.array([0.0, 0.0]), np.array([w - 1.0, h - 1.0])
    # clip both ends along the line to the frame (parametric Liang-Barsky on [0, 1] of a->b)
    t0, t1 = 0.0, 1.0
    v = b - a
    for k in range(2):
        if abs(v[k]) < 1e-12:
            continue
        ta, tb = (lo[k] - a[k]) / v[k], (hi[k] - a[k]) / v[k]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    if t1 <= t0:
        raise GeometryError("water line: the search line lies outside the frame")
    return np.array([a + t0 * v, a + t1 * v])


@dataclass
class LineActivity:
    """Streams frames and keeps, at samples along a line, the running mean and variance of the grey
    levels (Welford), averaged over ``half_width_px`` on each side of the line.

    Parameters
    ----------
    line_px : (2, 2) start and end of the search line (px), from one bank to the other.
    half_width_px : half width of the band averaged across the line (px).
    spacing_px : distance between samples along the line (px).
    """

    line_px: np.ndarray
    half_width_px: float = 4.0
    spacing_px: float = 1.0

    def __post_init__(self) -> None:
        p = np.asarray(self.line_px, float)
        if p.shape != (2, 2) or not np.all(np.isfinite(p)):
            raise ParameterError("water_level.search_line_px: give two [x, y] pixel points, one on each bank")
        length = float(np.hypot(*(p[1] - p[0])))
        if length < 20:
            raise GeometryError(f"water line: the search line is {length:.0f} px long; draw it across the whole river")
        self.line_px = p
        n = int(length / self.spacing_px) + 1
        t = np.linspace(0.0, 1.0, n)
        d = (p[1] - p[0]) / length
        normal = np.array([-d[1], d[0]])
        offs = np.arange(-self.half_width_px, self.half_width_px + 0.5, 1.0)
        pts = p[0][None, None] + t[:, None, None] * (p[1] - p[0])[None, None] + offs[None, :, None] * normal[None, None]
        self.map_x = pts[..., 0].astype(np.float32)
        self.map_y = pts[..., 1].astype(np.float32)
        self.t = t
        self.length_px = length
        self.n = 0
        self.mean = np.zeros(self.map_x.shape, np.float64)
        self.m2 = np.zeros(self.map_x.shape, np.float64)

    def add(self, gray: np.ndarray) -> None:
        """One gray frame (H x W, 0-255)."""
        v = cv2.remap(np.asarray(gray, np.float32), self.map_x, self.map_y, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        self.n += 1
        delta = v - self.mean
        self.mean += delta / self.n
        self.m2 += delta * (v - self.mean)

    def activity(self) -> np.ndarray:
        """Temporal standard deviation (grey levels) along the line, averaged across it."""
        if self.n < 3:
            raise GeometryError(f"water line: {self.n} frame(s) read; the detection needs at least 3")
        return np.sqrt(self.m2 / (self.n - 1)).mean(axis=1)


def find_edges(activity: np.ndarray, *, smooth: float = 1.0, min_contrast: float = 2.0) -> dict:
    """Left and right water edges in an activity profile (sample index units).

    Each sample is called water when its activity is above the geometric mean of the quieter bank's
    (an outer tenth of the line) and the water's (its middle), so a bank's sensor noise and slow, sparse water
    near an edge are told apart; the water is the stretch that holds the most more water than bank
    samples (maximum-sum run of +1 / -1), which a gap in the tracers inside the river does not break.
    Each edge is then placed at the crossing of that level, interpolated, with a 1-sigma from the
    steepness of the transition.

    Returns ``edges`` (2,) fractional indices, ``sigma`` (2,) their 1-sigma (samples), ``contrast``
    (water activity over the quieter bank's) and ``threshold``. Raises GeometryError when the water
    is not clearly more active than the banks, or a bank is not reached by the line.
    """
    a = gaussian_filter1d(np.asarray(activity, float), smooth, mode="nearest")
    n = len(a)
    if n < 20:
        raise GeometryError("water line: the search line is too short")
    k = max(n // 10, 2)
    bank = np.array([np.median(a[:k]), np.median(a[-k:])])
    water = float(np.median(a[int(0.3 * n): int(0.7 * n)]))
    quiet = max(float(bank.min()), 1e-6)  # the quieter end: a line whose other end is still on water says so below
    contrast = water / quiet
    if contrast < min_contrast:
        raise GeometryError(
            f"water line: could not find it; along the search line the water changes only {contrast:.1f}x more "
            f"than the banks over the clip (needed {min_contrast:g}x). Draw the line from bank to bank across "
            "moving water, or pick the water edges by hand (water_level.method = image)")
    la = np.log(np.maximum(a, 1e-6))
    th = 0.5 * (np.log(quiet) + np.log(water))
    w = np.where(la > th, 1.0, -1.0)
    # maximum-sum run (Kadane)
    best, cur, start, i0, i1 = -np.inf, 0.0, 0, 0, 0
    for i, v in enumerate(w):
        if cur <= 0:
            cur, start = v, i
        else:
            cur += v
        if cur > best:
            best, i0, i1 = cur, start, i
    if i0 == 0 or i1 == n - 1:
        name = "left" if i0 == 0 else "right"
        raise GeometryError(f"water line: the search line does not reach the {name} bank (the water is still "
                            "moving at its end); lengthen it onto the bank")
    if i1 - i0 < 0.1 * n:
        raise GeometryError("water line: the water found is a short stretch; the line may not cross the river")
    edges, sig = [], []
    lo_q, hi_q = th - 0.5 * (th - np.log(quiet)), th + 0.5 * (np.log(water) - th)
    for out, inn in ((i0 - 1, i0), (i1 + 1, i1)):
        ya, yb = la[inn], la[out]
        frac = (ya - th) / (ya - yb) if ya != yb else 0.5
        edges.append(inn + float(np.clip(frac, 0.0, 1.0)) * (out - inn))
        seg = la[max(min(inn, out) - 15, 0): max(inn, out) + 16]
        width = float(np.count_nonzero((seg > lo_q) & (seg < hi_q))) or 1.0
        sig.append(max(width / 1.35, 0.5))
    return {"edges": np.array(edges), "sigma": np.array(sig), "contrast": float(contrast), "threshold": float(np.exp(th)),
            "bank_activity": bank.tolist(), "water_activity": water}


def detect_water_edges(frames, line_px, *, half_width_px: float = 4.0, max_frames: int = 150) -> dict:
    """Water edges (px) along ``line_px`` from a stream of gray frames.

    Returns ``edges_px`` (2, 2) left, right (in the order of the line), ``sigma_px`` (2,) their 1-sigma
    along the line, ``contrast``, ``n_frames``, ``line_px`` and ``activity`` (the profile, for plots).
    """
    acc = LineActivity(np.asarray(line_px, float), half_width_px=half_width_px)
    for k, g in enumerate(frames):
        if k >= max_frames:
            break
        acc.add(g)
    prof = acc.activity()
    r = find_edges(prof)
    edges, sigma, refined = refine_on_mean(acc.mean.mean(axis=1), r["edges"], r["sigma"])
    p0, p1 = acc.line_px
    step = acc.length_px / (len(acc.t) - 1)
    pts = p0[None] + (edges[:, None] / (len(acc.t) - 1)) * (p1 - p0)[None]
    return {"edges_px": pts, "sigma_px": sigma * step, "contrast": r["contrast"], "n_frames": acc.n,
            "line_px": acc.line_px, "activity": prof, "bank_activity": r["bank_activity"],
            "water_activity": r["water_activity"], "refined_on_mean_image": refined.tolist()}


def refine_on_mean(mean: np.ndarray, edges: np.ndarray, sigma: np.ndarray, *, reach: float = 15.0,
                   min_strength: float = 4.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move each activity edge outwards to the strongest step of the time-averaged image, when that step
    stands out (``min_strength`` times the line's median step strength).

    Still water at a bank (the flow slows to nothing at the edge) is not active, so the activity edge
    lies inside the water, never outside it; the banks' look (wet soil, vegetation, shadow) usually
    differs from the water's in the mean image, whose step is then the edge. The search runs from 3
    samples inside the activity edge to ``max(reach, 4 sigma)`` samples outside. Returns edges, 1-sigma
    (samples) and which edges were moved.
    """
    m = np.asarray(mean, float)
    # step strength at each sample: difference of the means of the w samples on either side over their
    # pooled spread (a t-like statistic), so one textured speck on a bank does not count as the edge
    w = 6
    c = np.concatenate([[0.0], np.cumsum(m)])
    c2 = np.concatenate([[0.0], np.cumsum(m * m)])
    g = np.zeros(len(m))
    for j in range(w, len(m) - w):
        l_mu = (c[j] - c[j - w]) / w
        r_mu = (c[j + w] - c[j]) / w
        l_var = max((c2[j] - c2[j - w]) / w - l_mu**2, 0.0)
        r_var = max((c2[j + w] - c2[j]) / w - r_mu**2, 0.0)
        g[j] = abs(r_mu - l_mu) / np.sqrt(0.5 * (l_var + r_var) + 1.0)
    typical = float(np.median(g[w:-w])) + 1e-9
    out_e, out_s, moved = np.array(edges, float), np.array(sigma, float), np.zeros(2, bool)
    for k, e in enumerate(edges):
        far = max(reach, 4.0 * sigma[k])
        a, b = (e - far, e + 3.0) if k == 0 else (e - 3.0, e + far)
        lo, hi = int(max(np.floor(a), 1)), int(min(np.ceil(b), len(g) - 2))
        if hi <= lo:
            continue
        j = lo + int(np.argmax(g[lo:hi + 1]))
        if g[j] < min_strength * typical:
            continue
        y0, y1, y2 = g[j - 1], g[j], g[j + 1]
        den = y0 - 2 * y1 + y2
        off = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        out_e[k] = j + float(np.clip(off, -0.5, 0.5))
        out_s[k] = 1.0
        moved[k] = True
    return out_e, out_s, moved
