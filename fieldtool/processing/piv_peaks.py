"""Removal of the zero-displacement peak from ensemble correlation planes.

Whatever stays fixed in the image (glints flickering in place, standing waves, a codec's frozen blocks) adds a
correlation peak at zero displacement. With window deformation the final pass correlates in residual
coordinates around the predictor, so that peak sits at minus the predictor. Where the predictor says the node
moves (at least ``MIN_SHIFT_PX``), the plane supports a moving peak and a peak at absolute zero is not the
flow: the cells around it are set to the plane's median before the peak search, so the tracers' peak wins and
the fit of the peak never uses them (they lie at least ``MIN_SHIFT_PX - RADIUS_PX`` px from it).

The first pass of a multi-pass run has no predictor; it is blanked around zero on every plane when the pairs
are several frames apart (``frame_gap`` > 1: the first look found the slow nodes moving a few pixels per pair),
so that a fixed pattern cannot become the predictor of the next pass.
"""

from __future__ import annotations

import numpy as np

MIN_SHIFT_PX = 3.0  # predictor length (px) from which a peak at absolute zero is removed
RADIUS_PX = 1  # cells blanked around absolute zero (a (2r+1) x (2r+1) block)


def blank_zero(
    corr: np.ndarray,
    margin: int,
    pred_x: np.ndarray,
    pred_y: np.ndarray,
    min_shift: float = MIN_SHIFT_PX,
    radius: int = RADIUS_PX,
    fill: str = "median",
) -> np.ndarray:
    """Blank the block around absolute zero displacement in the planes of moving nodes (in place).

    Parameters
    ----------
    corr : (n, s, s) correlation planes; circular layout (index k = shift k, or k - s past s / 2) when
        ``margin == 0``, else index k = shift k - margin over the first 2 * margin + 1 cells.
    margin : the level's search margin (px).
    pred_x, pred_y : (n,) or (ny, nx) predictor of each node (px), the plane's origin.
    fill : "median" (the plane's median, for the final peak and its second peak) or "zero" (cheaper: the
        planes have zero mean; enough for a first pass, whose peak only predicts).

    Returns
    -------
    (n,) bool: nodes whose plane was blanked.
    """
    n, s, _ = corr.shape
    px, py = np.ravel(pred_x).astype(float), np.ravel(pred_y).astype(float)
    zx, zy = np.rint(-px).astype(int), np.rint(-py).astype(int)
    sel = np.isfinite(px) & np.isfinite(py) & (np.hypot(px, py) >= min_shift)
    if margin > 0:
        span = 2 * margin + 1
        ix, iy = zx + margin, zy + margin
        sel &= (ix >= 0) & (ix < span) & (iy >= 0) & (iy < span)
    else:
        half = s // 2
        sel &= (np.abs(zx) < half - radius) & (np.abs(zy) < half - radius)
        ix, iy = zx % s, zy % s
    nodes = np.flatnonzero(sel)
    if nodes.size == 0:
        return sel
    if fill == "median":
        values = np.median(corr[nodes].reshape(nodes.size, -1), axis=1).astype(corr.dtype)
    else:
        values = np.zeros(nodes.size, corr.dtype)
    lim = (2 * margin + 1) if margin > 0 else s
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            yy, xx = iy[nodes] + dy, ix[nodes] + dx
            if margin > 0:
                ok = (yy >= 0) & (yy < lim) & (xx >= 0) & (xx < lim)
                corr[nodes[ok], yy[ok], xx[ok]] = values[ok]
            else:
                corr[nodes, yy % s, xx % s] = values
    return sel
