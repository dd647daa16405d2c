"""Line plots drawn with OpenCV into an RGB image whose axes are known exactly (:class:`PlotAxes`),
so a click on the picture maps to data coordinates (the DEM-vs-bed plot of the Hellebaut method)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from fieldtool.viewer.mapping import PlotAxes


@dataclass
class Curve:
    """One polyline: ``x`` and ``y`` in data units, ``color`` RGB 0-255."""

    label: str
    x: np.ndarray
    y: np.ndarray
    color: tuple[int, int, int]


def _nice_ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
    span = hi - lo
    raw = span / max(n, 1)
    mag = 10 ** np.floor(np.log10(raw))
    step = min((s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw), default=10 * mag)
    return np.arange(np.ceil(lo / step) * step, hi + 1e-9 * span, step)


def render_plot(
    curves: list[Curve],
    *,
    size: tuple[int, int] = (1000, 600),
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    vlines: Sequence[tuple[float, tuple[int, int, int], str]] = (),
) -> tuple[np.ndarray, PlotAxes]:
    """Draw ``curves`` (and labelled vertical lines at x values) into a ``size`` = (width, height)
    RGB image. Returns the image and its :class:`PlotAxes`."""
    w, h = size
    left, right, top, bottom = 90, w - 30, 50, h - 70
    xs = np.concatenate([np.asarray(c.x, float) for c in curves] + [np.array([v[0] for v in vlines], float)])
    ys = np.concatenate([np.asarray(c.y, float) for c in curves])
    xs, ys = xs[np.isfinite(xs)], ys[np.isfinite(ys)]
    if not len(xs) or not len(ys):
        raise ValueError("nothing to plot")
    x0, x1 = float(xs.min()), float(xs.max())
    y0, y1 = float(ys.min()), float(ys.max())
    px, py = 0.03 * (x1 - x0 or 1.0), 0.08 * (y1 - y0 or 1.0)
    axes = PlotAxes(left, right, top, bottom, x0 - px, x1 + px, y0 - py, y1 + py)
    img = np.full((h, w, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for t in _nice_ticks(axes.x_min, axes.x_max):
        col = int(round(axes.data_to_px([[t, axes.y_min]])[0, 0]))
        cv2.line(img, (col, top), (col, bottom), (225, 225, 225), 1)
        cv2.putText(img, f"{t:g}", (col - 15, bottom + 22), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for t in _nice_ticks(axes.y_min, axes.y_max):
        r = int(round(axes.data_to_px([[axes.x_min, t]])[0, 1]))
        cv2.line(img, (left, r), (right, r), (225, 225, 225), 1)
        cv2.putText(img, f"{t:g}", (8, r + 5), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (right, bottom), (0, 0, 0), 1)
    for c in curves:
        p = axes.data_to_px(np.c_[c.x, c.y])
        ok = np.all(np.isfinite(p), axis=1)
        pts = np.round(p[ok] * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, c.color, 2, cv2.LINE_AA, shift=4)
    for x, color, label in vlines:
        col = int(round(axes.data_to_px([[x, axes.y_min]])[0, 0]))
        for r in range(top, bottom, 12):
            cv2.line(img, (col, r), (col, min(r + 6, bottom)), color, 2)
        cv2.putText(img, label, (col + 4, top + 16), font, 0.5, color, 1, cv2.LINE_AA)
    cv2.putText(img, title, (left, 30), font, 0.7, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, ((left + right) // 2 - 60, h - 25), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (8, top - 12), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    lx = right - 220
    for i, c in enumerate(curves):
        yy = top + 20 + 20 * i
        cv2.line(img, (lx, yy), (lx + 30, yy), c.color, 2)
        cv2.putText(img, c.label, (lx + 38, yy + 5), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img, axes
