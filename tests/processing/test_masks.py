"""ROI rectangle and mask polygons."""

from __future__ import annotations

import numpy as np
import pytest

from fieldtool.errors import ParameterError
from fieldtool.processing.masks import check_roi, masked_at, rasterize


def _inside(poly: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Even-odd crossing test (independent of OpenCV)."""
    inside = np.zeros(x.shape, bool)
    n = len(poly)
    for i in range(n):
        x0, y0 = poly[i]
        x1, y1 = poly[(i + 1) % n]
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < xc)
    return inside


def test_rasterize_matches_point_in_polygon():
    h, w = 120, 160
    polys = [[[10.2, 15.7], [90.4, 20.1], [60.3, 100.8]], [[100, 10], [150, 10], [150, 60], [125, 30], [100, 60]]]
    mask = rasterize((h, w), polys)
    assert mask.shape == (h, w) and mask.dtype == bool
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    truth = _inside(np.array(polys[0], float), xx, yy) | _inside(np.array(polys[1], float), xx, yy)
    # pixels whose centre is within half a pixel of an edge may go either way
    assert (mask != truth).sum() <= 0.05 * truth.sum()
    assert mask[60, 55] and mask[20, 110] and not mask[50, 125] and not mask[110, 5]


def test_rasterize_empty_list_masks_nothing():
    assert not rasterize((10, 12), []).any()


def test_polygon_with_too_few_points():
    with pytest.raises(ParameterError, match=r"roi.masks_px\[1\]: a mask polygon needs at least 3 points, got 2"):
        rasterize((50, 50), [[[1, 1], [10, 1], [5, 8]], [[1, 1], [10, 10]]])
    with pytest.raises(ParameterError, match="got 0"):
        rasterize((50, 50), [[]])


def test_degenerate_or_malformed_polygon():
    with pytest.raises(ParameterError, match=r"roi.masks_px\[0\]: the polygon has no area"):
        rasterize((50, 50), [[[0, 0], [10, 10], [20, 20]]])
    with pytest.raises(ParameterError, match=r"list of \[x, y\]"):
        rasterize((50, 50), [[[0, 0, 1], [10, 10, 1], [20, 0, 1]]])
    with pytest.raises(ParameterError, match="not a number"):
        rasterize((50, 50), [[[0, 0], [10, float("nan")], [20, 0]]])


def test_check_roi():
    shape = (720, 1280)
    assert check_roi([], shape) == (0, 0, 1280, 720)
    assert check_roi([100, 50, 300.4, 200.6], shape) == (100, 50, 301, 202)
    assert check_roi([300, 200, 100, 50], shape) == (100, 50, 301, 201)  # corners in any order
    assert check_roi([-0.5, -0.5, 1279.5, 719.5], shape) == (0, 0, 1280, 720)


def test_check_roi_errors():
    shape = (720, 1280)
    with pytest.raises(ParameterError, match=r"roi.rect_px: .* reaches outside the 1280 x 720 px frame"):
        check_roi([100, 50, 1400, 200], shape)
    with pytest.raises(ParameterError, match="empty"):
        check_roi([100, 50, 100, 200], shape)
    with pytest.raises(ParameterError, match="four numbers"):
        check_roi([1, 2, 3], shape)
    with pytest.raises(ParameterError, match="not a number"):
        check_roi([1, 2, float("inf"), 5], shape)


def test_masked_at():
    mask = rasterize((40, 60), [[[10, 10], [30, 10], [30, 30], [10, 30]]])
    x = np.array([20.2, 5.0, 59.4, 70.0, -1.0])
    y = np.array([19.7, 5.0, 39.0, 5.0, 5.0])
    assert masked_at(mask, x, y).tolist() == [True, False, False, True, True]  # outside the frame = invalid
