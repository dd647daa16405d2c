"""Region of interest and masks (thesis 9.2.6).

The ROI is a rectangle of the frame where PIV runs; masks are polygons whose vectors are invalid
(left out of the discharge, never interpolated into it). Coordinates are image pixels: x right,
y down, origin at the centre of the top-left pixel, so the frame covers -0.5 .. W-0.5 in x.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from fieldtool.errors import ParameterError

_SHIFT = 4  # cv2.fillPoly fixed-point bits: vertices placed to 1/16 px


def check_polygon(poly, key: str) -> np.ndarray:
    """A polygon as an (N, 2) float array (px); ParameterError naming ``key`` if unusable."""
    try:
        arr = np.asarray(poly, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError(f"{key}: a polygon is a list of [x, y] pixel points, got {poly!r}") from None
    if arr.size == 0:
        arr = arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ParameterError(f"{key}: a polygon is a list of [x, y] pixel points, got {poly!r}")
    if len(arr) < 3:
        raise ParameterError(
            f"{key}: a mask polygon needs at least 3 points, got {len(arr)}; click three or more corners around "
            "the area to exclude, or remove the mask"
        )
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{key}: a point is not a number")
    x, y = arr[:, 0], arr[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    if area < 1.0:
        raise ParameterError(f"{key}: the polygon has no area (its points lie on a line); redraw it")
    return arr


def rasterize(shape: tuple[int, int], polygons: list[list[list[float]]], key: str = "roi.masks_px") -> np.ndarray:
    """Boolean image of the masked pixels.

    Parameters
    ----------
    shape : (height, width) of the frame (px).
    polygons : polygons, each a list of [x, y] pixel vertices (at least 3).
    key : project key named in error messages.

    Returns
    -------
    (H, W) bool, True where a pixel centre lies inside any polygon.

    Raises
    ------
    ParameterError : a polygon with fewer than 3 points, no area, or non-numeric points,
        naming it as ``key[i]``.
    """
    h, w = int(shape[0]), int(shape[1])
    out = np.zeros((h, w), np.uint8)
    polys = [check_polygon(p, f"{key}[{i}]") for i, p in enumerate(polygons)]
    if polys:
        pts = [np.round(p * (1 << _SHIFT)).astype(np.int32) for p in polys]
        cv2.fillPoly(out, pts, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return out.astype(bool)


def check_roi(rect_px, shape: tuple[int, int], key: str = "roi.rect_px") -> tuple[int, int, int, int]:
    """Validate a rectangular ROI and return it as integer slice bounds.

    Parameters
    ----------
    rect_px : [x0, y0, x1, y1] two opposite corners (px, pixel centres, any order); [] = whole frame.
    shape : (height, width) of the frame (px).
    key : project key named in error messages.

    Returns
    -------
    (x0, y0, x1, y1) ints with ``frame[y0:y1, x0:x1]`` the ROI; both clicked pixels are inside.

    Raises
    ------
    ParameterError : not 4 numbers, outside the frame, or smaller than 2 x 2 px.
    """
    h, w = int(shape[0]), int(shape[1])
    if rect_px is None or len(rect_px) == 0:
        return 0, 0, w, h
    try:
        x0, y0, x1, y1 = (float(v) for v in rect_px)
    except (TypeError, ValueError):
        raise ParameterError(f"{key}: give four numbers [x0, y0, x1, y1] in pixels, got {rect_px!r}") from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise ParameterError(f"{key}: {list(rect_px)} contains a value that is not a number")
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    if x0 < -0.5 or y0 < -0.5 or x1 > w - 0.5 or y1 > h - 0.5:
        raise ParameterError(
            f"{key}: [{x0:g}, {y0:g}, {x1:g}, {y1:g}] reaches outside the {w} x {h} px frame "
            f"(x from 0 to {w - 1}, y from 0 to {h - 1}); pick the corners inside the image"
        )
    ix0, iy0 = int(math.floor(x0 + 0.5)), int(math.floor(y0 + 0.5))
    ix1, iy1 = int(math.floor(x1 + 0.5)) + 1, int(math.floor(y1 + 0.5)) + 1
    ix1, iy1 = min(ix1, w), min(iy1, h)
    if ix1 - ix0 < 2 or iy1 - iy0 < 2:
        raise ParameterError(
            f"{key}: the ROI is {ix1 - ix0} x {iy1 - iy0} px, which is empty; pick its top-left and "
            "bottom-right corners"
        )
    return ix0, iy0, ix1, iy1


def masked_at(mask: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """True where the nearest pixel to (x, y) is masked or lies outside the frame.

    Used to invalidate PIV vectors: x, y are node positions (px) in the frame ``mask`` covers.
    """
    xi = np.rint(np.asarray(x, float)).astype(int)
    yi = np.rint(np.asarray(y, float)).astype(int)
    h, w = mask.shape
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    out = np.ones(np.broadcast(xi, yi).shape, bool)
    out[inside] = mask[yi[inside], xi[inside]]
    return out
