"""Snap a click to the centre of a nearby checker target (the 2x2 GCP targets), to a fraction of a pixel.

A checker target's centre is a saddle point of the image intensity: around it, a small circle
crosses dark, bright, dark, bright. :func:`snap_to_target` looks for such a point near the click:

1. candidates: local maxima of the saddle strength ``-det(Hessian)`` of the smoothed image within
   ``radius_px`` of the click;
2. each is refined by Newton steps to the saddle point of the smoothed intensity (gradient zero,
   negative Hessian determinant): on a point-symmetric target the smoothing keeps the saddle at
   the centre, so it lands within a fraction of a pixel (0.17 px at worst on the demo's smallest,
   most foreshortened target, where cv2.cornerSubPix was 0.75 px off);
3. the refined point is tested on rings of a few pixels' radius (the ChESS idea: the intensity
   along two neighbouring rings must be dominated by its two-cycles-per-turn component, with a
   strong contrast and the same phase); the passing point nearest the click wins;
4. a target seen at a grazing angle (the far bank of ``far_bank``: 26 px wide, 5 px high) is
   thinner than the rings, which then leave it and fail: when the circles fail, the rings are
   drawn again as ellipses of the target's apparent shape, taken from the structure tensor of the
   smoothed image around the point (the axis across the strongest edges shortened by the square
   root of the tensor's eigenvalue ratio, the other lengthened by it, up to MAX_ELONGATION).
   An ellipse of the target's shape is the image of a circle on the target, so the same test holds.

Strongly textured ground has saddles too: on the synthetic demo's banks about one click in
ten that lands 8 px or less from such a texture saddle snaps to it, so the viewer reports every
snap (and how far it moved the click) and Undo takes it back.

Image coordinates follow OpenCV (x right, y down, origin at the centre of the top-left pixel).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

RING_RADII_PX = (2.0, 3.0, 4.5, 6.5)
MIN_DOMINANCE = 0.6  # share of the ring's variation in its 2-cycle component
MIN_CONTRAST = 40.0  # grey levels (0..255): amplitude of the dark/bright alternation on the ring
SMOOTH_PX = 0.8  # Gaussian sigma of the smoothing the saddle is taken on
MAX_TWIST_RAD = np.deg2rad(25.0)  # phase change allowed between neighbouring rings
SHAPE_SIGMA_PX = 5.0  # Gaussian window (sigma, px) of the structure tensor that gives a target's apparent shape
MAX_ELONGATION = 6.0  # largest eigenvalue ratio of that tensor used (an ellipse up to sqrt(6) = 2.4 : 1 per axis)


@dataclass(frozen=True)
class Snap:
    """A detected target centre (pixels), its distance from the click (px) and its score (0..1)."""

    x: float
    y: float
    moved_px: float
    score: float


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32)


def _ring(
    g: np.ndarray, x: float, y: float, r: float, shape: np.ndarray | None = None, n: int = 32
) -> tuple[float, float, float]:
    """(dominance, contrast, phase) of the two-cycles-per-turn pattern on a ring of radius r: a circle, or
    the ellipse ``shape @ circle`` (``shape`` a 2x2 matrix, px per px)."""
    th = np.arange(n) * 2 * np.pi / n
    p = np.vstack([r * np.cos(th), r * np.sin(th)])
    if shape is not None:
        p = shape @ p
    mx = (x + p[0]).astype(np.float32)[None, :]
    my = (y + p[1]).astype(np.float32)[None, :]
    vals = cv2.remap(g, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0].astype(float)
    c = np.fft.rfft(vals - vals.mean()) / n
    power = np.abs(c[1:]) ** 2
    total = float(power.sum())
    if total <= 0:
        return 0.0, 0.0, 0.0
    return float(power[1] / total), float(2 * np.abs(c[2])), float(np.angle(c[2]))


def _shape(tensor: dict[str, np.ndarray], x: float, y: float) -> np.ndarray | None:
    """The 2x2 matrix that maps a circle onto the apparent shape of a target centred at (x, y): the
    structure tensor's strong axis (across the target's long edges) shortened by sqrt(ratio) and the weak
    axis lengthened by it (area kept). None when the tensor is (nearly) round: the circles were the test."""

    def at(name: str) -> float:
        return float(cv2.getRectSubPix(tensor[name], (1, 1), (x, y))[0, 0])

    j = np.array([[at("xx"), at("xy")], [at("xy"), at("yy")]])
    lam, vec = np.linalg.eigh(j)
    if lam[1] <= 0:
        return None
    q = min(lam[1] / max(lam[0], lam[1] * 1e-6), MAX_ELONGATION)
    if q < 1.5:
        return None
    return np.column_stack([vec[:, 0] * np.sqrt(q), vec[:, 1] / np.sqrt(q)])


def _ring_score(g: np.ndarray, x: float, y: float, shape: np.ndarray | None = None) -> float:
    """0 when (x, y) is not the centre of a checker target, else a score in (0, 1].

    Neighbouring rings must all be dominated by the two-cycle pattern, with a contrast above
    MIN_CONTRAST and the same phase (the target's edges are straight lines through its centre; a
    textured bank's saddles twist from one radius to the next): two circles, or three ellipses
    ``shape @ circle`` (the shape is fitted to the point, so it must hold over one ring more)."""
    rings = [_ring(g, x, y, r, shape) for r in RING_RADII_PX]
    run = 2 if shape is None else 3
    best = 0.0
    for i in range(len(rings) - run + 1):
        part = rings[i : i + run]
        dom, con = min(r[0] for r in part), min(r[1] for r in part)
        twist = max(abs(np.angle(np.exp(1j * (a[2] - b[2])))) for a, b in itertools.pairwise(part))
        if dom >= MIN_DOMINANCE and con >= MIN_CONTRAST and twist < MAX_TWIST_RAD:
            best = max(best, dom * (1 - twist / np.pi))
    return best


def _saddle(d: dict[str, np.ndarray], x: float, y: float, iters: int = 12) -> tuple[float, float] | None:
    """Newton steps to the saddle point of the smoothed intensity (gradient zero, det(H) < 0)."""

    def at(name: str, px: float, py: float) -> float:
        return float(cv2.getRectSubPix(d[name], (1, 1), (px, py))[0, 0])

    for _ in range(iters):
        hxx, hxy, hyy = at("xx", x, y), at("xy", x, y), at("yy", x, y)
        det = hxx * hyy - hxy * hxy
        if det >= 0:
            return None
        gx, gy = at("x", x, y), at("y", x, y)
        sx = -(hyy * gx - hxy * gy) / det
        sy = -(-hxy * gx + hxx * gy) / det
        sx, sy = float(np.clip(sx, -1, 1)), float(np.clip(sy, -1, 1))
        x, y = x + sx, y + sy
        if np.hypot(sx, sy) < 1e-3:
            return x, y
    return None


def snap_to_target(image: np.ndarray, x: float, y: float, radius_px: float = 8.0) -> Snap | None:
    """The centre of a checker target within ``radius_px`` of the click (x, y), or None.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) RGB image, uint8 grey levels.
    x, y : the click, pixels.
    radius_px : how far from the click a target centre may lie, pixels.

    Returns
    -------
    Snap with the sub-pixel centre, or None when no target passes the ring test.
    """
    g = _gray(image)
    h, w = g.shape
    pad = int(radius_px + max(RING_RADII_PX) + 8)
    x0, y0 = max(int(x) - pad, 0), max(int(y) - pad, 0)
    x1, y1 = min(int(x) + pad + 1, w), min(int(y) + pad + 1, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    sm = cv2.GaussianBlur(g[y0:y1, x0:x1], (0, 0), SMOOTH_PX)
    d = {
        "x": cv2.Sobel(sm, cv2.CV_32F, 1, 0, ksize=3) / 8,
        "y": cv2.Sobel(sm, cv2.CV_32F, 0, 1, ksize=3) / 8,
        "xx": cv2.Sobel(sm, cv2.CV_32F, 2, 0, ksize=3) / 4,
        "yy": cv2.Sobel(sm, cv2.CV_32F, 0, 2, ksize=3) / 4,
        "xy": cv2.Sobel(sm, cv2.CV_32F, 1, 1, ksize=3) / 4,
    }
    tensor = {
        k: cv2.GaussianBlur(a * b, (0, 0), SHAPE_SIGMA_PX)
        for k, a, b in (("xx", d["x"], d["x"]), ("xy", d["x"], d["y"]), ("yy", d["y"], d["y"]))
    }
    sad = -(d["xx"] * d["yy"] - d["xy"] * d["xy"])
    peaks = (sad > 0) & (sad >= cv2.dilate(sad, np.ones((3, 3), np.uint8)))
    yy, xx = np.nonzero(peaks)
    near = np.hypot(xx + x0 - x, yy + y0 - y) <= radius_px + 1
    yy, xx = yy[near], xx[near]
    order = np.argsort(-sad[yy, xx])[:16]
    best: tuple[float, float, float] | None = None
    for k in order:
        found = _saddle(d, float(xx[k]), float(yy[k]))
        if found is None:
            continue
        rx, ry = found[0] + x0, found[1] + y0
        if np.hypot(rx - xx[k] - x0, ry - yy[k] - y0) > 2.5 or np.hypot(rx - x, ry - y) > radius_px:
            continue  # it wandered off: not a clean saddle
        score = _ring_score(sm, rx - x0, ry - y0)
        if score == 0:  # a target seen at a grazing angle: rings of its apparent shape
            shape = _shape(tensor, rx - x0, ry - y0)
            score = _ring_score(sm, rx - x0, ry - y0, shape) if shape is not None else 0.0
        if score > 0 and (best is None or np.hypot(rx - x, ry - y) < np.hypot(best[0] - x, best[1] - y) - 1e-6):
            best = (rx, ry, score)  # the passing saddle nearest the click: the one the operator aimed at
    if best is None:
        return None
    rx, ry, score = best
    return Snap(rx, ry, float(np.hypot(rx - x, ry - y)), float(score))
