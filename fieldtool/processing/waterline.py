"""Automatic water line: the water edges along a search line across the river, found in the video.

Flowing water changes from frame to frame (tracers, ripples, glints); banks do not. Along a search line
that crosses the river from bank to bank, the temporal standard deviation of the grey levels (averaged
over a thin band across the line) is high over the water and low over the banks. The water edges are
where that activity falls from the water's level to the bank's (see :func:`find_edges`). Still water at a
bank is not active, so each edge then walks outwards over still water onto the bank and snaps to the step of
the time-averaged image (:func:`settle_on_bank`). The same is done on parallel lines a few decimetres apart
on the water plane (:func:`parallel_lines`); with the ortho mapping and the cross-section each line's edges
give a width and so a level, and the lines must agree (``processing.water_level.waterline_level``), as the
thesis' image method (5.3) without clicks.

Image space: working-image pixels (undistorted), x right, y down. Intensities 0-255.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from fieldtool.errors import GeometryError, ParameterError


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
        v = cv2.remap(
            np.asarray(gray, np.float32), self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        ).astype(np.float64)
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
    water = float(np.median(a[int(0.3 * n) : int(0.7 * n)]))
    quiet = max(float(bank.min()), 1e-6)  # the quieter end: a line whose other end is still on water says so below
    contrast = water / quiet
    if contrast < min_contrast:
        raise GeometryError(
            f"water line: could not find it; along the search line the water changes only {contrast:.1f}x more "
            f"than the banks over the clip (needed {min_contrast:g}x). Draw the line from bank to bank across "
            "moving water, or pick the water edges by hand (water_level.method = image)"
        )
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
        raise GeometryError(
            f"water line: the search line does not reach the {name} bank (the water is still "
            "moving at its end); lengthen it onto the bank"
        )
    if i1 - i0 < 0.1 * n:
        raise GeometryError("water line: the water found is a short stretch; the line may not cross the river")
    edges, sig = [], []
    lo_q, hi_q = th - 0.5 * (th - np.log(quiet)), th + 0.5 * (np.log(water) - th)
    for out, inn in ((i0 - 1, i0), (i1 + 1, i1)):
        ya, yb = la[inn], la[out]
        frac = (ya - th) / (ya - yb) if ya != yb else 0.5
        edges.append(inn + float(np.clip(frac, 0.0, 1.0)) * (out - inn))
        seg = la[max(min(inn, out) - 15, 0) : max(inn, out) + 16]
        width = float(np.count_nonzero((seg > lo_q) & (seg < hi_q))) or 1.0
        sig.append(max(width / 1.35, 0.5))
    return {
        "edges": np.array(edges),
        "sigma": np.array(sig),
        "contrast": float(contrast),
        "threshold": float(np.exp(th)),
        "bank_activity": bank.tolist(),
        "water_activity": water,
    }


def _robust(x: np.ndarray, floor: float) -> tuple[float, float]:
    """Median and MAD-based spread (floored) of ``x``."""
    med = float(np.median(x))
    return med, max(1.4826 * float(np.median(np.abs(x - med))), floor)


EDGE_SIGMA_SAMPLES = 1.5  # 1-sigma of an edge settled on the bank (samples): on 300 synthetic lines, median
# error 0.23 samples, 90th percentile 2.3 (benchmarks/waterline_accuracy.py)


def _step(c: np.ndarray, b: int, w: int) -> float:
    """|mean of the w samples from b| - |mean of the w samples before b| from the cumulative sum ``c``."""
    return abs((c[b + w] - c[b]) / w - (c[b] - c[b - w]) / w)


def settle_on_bank(
    mean: np.ndarray,
    texture: np.ndarray,
    activity: np.ndarray,
    threshold: float,
    edges: np.ndarray,
    *,
    run: int = 3,
    snap: int = 3,
    w: int = 3,
) -> dict:
    """Move each activity edge outwards over still water onto the bank, then onto the step of the mean image.

    Still water at a bank (the flow slows to nothing at the edge, no tracer passes) is not active, so the
    activity edge lies inside the water, never outside it; a tracer-free stretch may also cut an active
    strip along the bank off the main one. Outwards from each activity edge, a sample is water when it is
    active (above ``threshold``) or still: smoother in the time-averaged image (``texture``, the spread of
    the mean image across the line) than the 10th percentile of that side's bank (the outer tenth of the
    line), with a mean grey level within the active water's (median - 5 / + 2 robust spreads). The bank
    starts at the first ``run`` samples in a row that are neither; the edge then snaps to the strongest
    step of the mean image (difference of the ``w``-sample means on either side) within ``snap`` samples.

    Returns ``edges`` (2,) fractional samples, ``sigma`` (2,), ``still_water`` (samples walked on each
    side). Raises GeometryError when the walk reaches the end of the line (no bank found).
    """
    raw = np.asarray(mean, float)
    m = gaussian_filter1d(raw, 1.0, mode="nearest")
    lt = gaussian_filter1d(np.log(np.asarray(texture, float) + 0.5), 1.0, mode="nearest")
    active = gaussian_filter1d(np.asarray(activity, float), 1.0, mode="nearest") > threshold
    n = len(m)
    k = max(n // 10, 2)
    i0, i1 = int(np.ceil(edges[0])), int(np.floor(edges[1]))
    wm, ws = _robust(m[i0 + 3 : max(i1 - 2, i0 + 4)], 2.0)
    c = np.concatenate([[0.0], np.cumsum(raw)])
    out, still = np.array(edges, float), [0, 0]
    for side in (0, 1):
        bank = slice(0, k) if side == 0 else slice(n - k, n)
        smooth = lt < np.percentile(lt[bank], 10)
        water = active | (smooth & (m < wm + 2 * ws) & (m > wm - 5 * ws))
        step = -1 if side == 0 else 1
        j = start = (i0 - 1) if side == 0 else (i1 + 1)
        while 0 <= j < n and any(water[q] for q in range(j, j + step * run, step) if 0 <= q < n):
            j += step
        if not 0 <= j < n:
            name = "left" if side == 0 else "right"
            raise GeometryError(
                f"water line: still water reaches the {name} end of the search line; lengthen it onto the bank"
            )
        still[side] = abs(j - start)
        pos = j - 0.5 * step  # between the last water sample and the first bank sample
        cand = [b for b in range(int(np.floor(pos - snap)), int(np.ceil(pos + snap)) + 1) if b - w >= 0 and b + w <= n]
        if cand:
            out[side] = max(cand, key=lambda b: _step(c, b, w)) - 0.5  # between samples b - 1 and b
        else:
            out[side] = pos
    return {"edges": out, "sigma": np.full(2, EDGE_SIGMA_SAMPLES), "still_water": still}


def station_function(section_px: np.ndarray, mapping, station_offset_m: float):
    """Water-plane points (N, 2) m -> cross-section stations (m): the distance along the section (two
    working-image points, the first at ``station_offset_m``) from its first point."""
    pw = mapping.image_to_world(np.asarray(section_px, float))
    u = (pw[1] - pw[0]) / max(float(np.hypot(*(pw[1] - pw[0]))), 1e-12)
    return lambda w: station_offset_m + (np.asarray(w, float) - pw[0]) @ u


def parallel_lines(line_px: np.ndarray, mapping, spacing_m: float, n_side: int, shape: tuple[int, int]) -> list:
    """The search line and ``n_side`` lines on each side of it, ``spacing_m`` apart on the water plane
    (shifted along the plane's normal to the line, mapped back to the image and clipped to the frame).
    Returns a list of (offset_m, (2, 2) px); the centre line first."""
    p = np.asarray(line_px, float)
    out = [(0.0, p)]
    if n_side < 1 or spacing_m <= 0:
        return out
    w = mapping.image_to_world(p)
    d = w[1] - w[0]
    nrm = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-12)
    for k in range(1, n_side + 1):
        for sgn in (-1, 1):
            off = sgn * k * spacing_m
            try:
                q = mapping.world_to_image(w + off * nrm[None])
                if np.all(np.isfinite(q)):
                    out.append((off, extend_line(q[0], q[1], 0.0, shape)))
            except GeometryError:
                pass
    return out


def detect_water_edges(frames, lines, *, half_width_px: float = 4.0, max_frames: int = 150) -> dict:
    """Water edges (px) along each search line from one stream of gray frames.

    ``lines``: a (2, 2) line, or a list of (offset_m, (2, 2) px) from :func:`parallel_lines` (centre first).
    Returns ``lines``: per line a dict with ``offset_m``, ``line_px`` and either ``error`` (why no edge was
    found on it) or ``edges_px`` (2, 2) left, right (in the order of the line), ``sigma_px`` (2,) their
    1-sigma along the line, ``contrast``, ``still_water_px`` (px walked over still water on each side); and, for the
    centre line, ``activity`` and ``mean`` profiles (for plots). Also ``n_frames``.
    """
    if isinstance(lines, np.ndarray) or (len(lines) == 2 and np.shape(lines[0]) == (2,)):
        lines = [(0.0, np.asarray(lines, float))]
    accs = [LineActivity(np.asarray(ln, float), half_width_px=half_width_px) for _, ln in lines]
    for k, g in enumerate(frames):
        if k >= max_frames:
            break
        for a in accs:
            a.add(g)
    out: list = []
    for (off, _), acc in zip(lines, accs, strict=True):
        prof = acc.activity()
        mean = acc.mean.mean(axis=1)
        item = {"offset_m": float(off), "line_px": acc.line_px}
        if not out:
            item.update(activity=prof, mean=mean)
        try:
            r = find_edges(prof)
            s = settle_on_bank(mean, acc.mean.std(axis=1), prof, r["threshold"], r["edges"])
        except GeometryError as e:
            item["error"] = str(e)
            out.append(item)
            continue
        p0, p1 = acc.line_px
        step = acc.length_px / (len(acc.t) - 1)
        pts = p0[None] + (s["edges"][:, None] / (len(acc.t) - 1)) * (p1 - p0)[None]
        item.update(
            edges_px=pts,
            sigma_px=s["sigma"] * step,
            contrast=r["contrast"],
            still_water_px=[float(v * step) for v in s["still_water"]],
            bank_activity=r["bank_activity"],
            water_activity=r["water_activity"],
        )
        out.append(item)
    return {"lines": out, "n_frames": accs[0].n}
