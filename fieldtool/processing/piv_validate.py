"""Vector validation and replacement for PIV fields (thesis 2.2.4 "Vectors validation and interpolation").

All functions work on one field of node values, arrays of shape (ny, nx), with NaN marking a vector
that is already invalid. Displacements are in pixels (image axes: +x right, +y down) unless stated.
The tests return a boolean array, True = the vector passes; they never modify their input.
"""

from __future__ import annotations

import numpy as np

#: Residual floor of the normalised median test (Westerweel & Scarano 2005), in pixels.
MEDIAN_EPS_PX = 0.1

_NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def _neighbour_stack(a: np.ndarray) -> np.ndarray:
    """The 8 neighbours of every node, shape (8, ny, nx); NaN outside the grid."""
    ny, nx = a.shape
    p = np.full((ny + 2, nx + 2), np.nan, dtype=np.float64)
    p[1:-1, 1:-1] = a
    return np.stack([p[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] for dy, dx in _NEIGHBOURS])


def _nanmedian0(stack: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN, NaN where all are NaN (no RuntimeWarning)."""
    s = np.sort(stack, axis=0)  # NaN sort last
    n = np.sum(~np.isnan(stack), axis=0)
    lo = np.clip((n - 1) // 2, 0, None)
    hi = np.clip(n // 2, 0, None)
    a = np.take_along_axis(s, lo[None], axis=0)[0]
    b = np.take_along_axis(s, hi[None], axis=0)[0]
    out = 0.5 * (a + b)
    out[n == 0] = np.nan
    return out


def normalized_median_test(
    u: np.ndarray, v: np.ndarray, threshold: float = 2.0, eps: float = MEDIAN_EPS_PX, min_neighbours: int = 3
) -> np.ndarray:
    """Normalised local median test (Westerweel & Scarano 2005) over the 8 neighbours.

    Parameters
    ----------
    u, v : (ny, nx) displacements in pixels; NaN = invalid (ignored as neighbour).
    threshold : normalised residual above which a vector fails (typically 2).
    eps : residual floor in pixels (mean noise level of the correlation, ~0.1 px).
    min_neighbours : a vector with fewer valid neighbours than this is not judged (passes).

    Returns
    -------
    ok : (ny, nx) bool, True where the vector passes (NaN input -> False).
    """
    ok = np.isfinite(u) & np.isfinite(v)
    r_max = np.zeros(u.shape)
    for comp in (u, v):
        nb = _neighbour_stack(comp)
        med = _nanmedian0(nb)
        rm = _nanmedian0(np.abs(nb - med[None]))
        r = np.abs(comp - med) / (rm + eps)
        r_max = np.fmax(r_max, np.nan_to_num(r, nan=0.0))
    n_valid = np.sum(np.isfinite(_neighbour_stack(u)) & np.isfinite(_neighbour_stack(v)), axis=0)
    judged = n_valid >= min_neighbours
    return ok & ~(judged & (r_max > threshold))


def global_std_test(u: np.ndarray, v: np.ndarray, n_sigma: float = 4.0) -> np.ndarray:
    """Global standard-deviation test: a vector fails if a component lies outside mean ± n_sigma·std.

    Parameters
    ----------
    u, v : (ny, nx) velocities or displacements (any unit, same for both); NaN = invalid.
    n_sigma : width of the accepted band in standard deviations.

    Returns
    -------
    ok : (ny, nx) bool, True where the vector passes (NaN input -> False).
    """
    ok = np.isfinite(u) & np.isfinite(v)
    if ok.sum() < 3:
        return ok
    for comp in (u, v):
        vals = comp[ok]
        mu, sd = float(vals.mean()), float(vals.std())
        with np.errstate(invalid="ignore"):
            ok &= np.abs(comp - mu) <= n_sigma * sd + 1e-12
    return ok


def speed_test(u: np.ndarray, v: np.ndarray, max_speed: np.ndarray | float | None) -> np.ndarray:
    """Velocity limit: a vector fails if its magnitude exceeds ``max_speed`` (same unit as u, v; per node or scalar).

    Returns (ny, nx) bool, True where the vector passes; a NaN or infinite limit never rejects.
    """
    ok = np.isfinite(u) & np.isfinite(v)
    if max_speed is None:
        return ok
    lim = np.broadcast_to(np.asarray(max_speed, dtype=np.float64), u.shape)
    with np.errstate(invalid="ignore"):
        too_fast = np.hypot(u, v) > lim
    return ok & ~(too_fast & np.isfinite(lim))


def replace_invalid(
    u: np.ndarray, v: np.ndarray, keep_invalid: np.ndarray | None = None, min_neighbours: int = 3, max_iter: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replace invalid vectors by the mean of their valid neighbours, only where enough neighbours are valid.

    Parameters
    ----------
    u, v : (ny, nx) fields, NaN = invalid.
    keep_invalid : (ny, nx) bool, nodes that must stay invalid (masked area); never filled, never used.
    min_neighbours : valid 8-neighbours a node needs to be replaced.
    max_iter : replacement sweeps; each sweep may use nodes replaced in the previous one.

    Returns
    -------
    u2, v2 : the fields with replacements (NaN where still invalid).
    replaced : (ny, nx) bool, True where a value was filled in.
    """
    u2 = np.array(u, dtype=np.float64)
    v2 = np.array(v, dtype=np.float64)
    replaced = np.zeros(u.shape, dtype=bool)
    if keep_invalid is not None:
        u2[keep_invalid] = np.nan
        v2[keep_invalid] = np.nan
    for _ in range(max_iter):
        bad = ~(np.isfinite(u2) & np.isfinite(v2))
        if keep_invalid is not None:
            bad &= ~keep_invalid
        if not bad.any():
            break
        nu, nv = _neighbour_stack(u2), _neighbour_stack(v2)
        good = np.isfinite(nu) & np.isfinite(nv)
        n = good.sum(axis=0)
        fill = bad & (n >= min_neighbours)
        if not fill.any():
            break
        su = np.where(good, nu, 0.0).sum(axis=0)
        sv = np.where(good, nv, 0.0).sum(axis=0)
        u2[fill] = su[fill] / n[fill]
        v2[fill] = sv[fill] / n[fill]
        replaced |= fill
    return u2, v2, replaced


def fill_all(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill every NaN (for a multi-pass predictor): neighbour means grown outwards, then the field median, then 0."""
    u2, v2 = np.array(u, dtype=np.float64), np.array(v, dtype=np.float64)
    for _ in range(max(u.shape)):
        bad = ~(np.isfinite(u2) & np.isfinite(v2))
        if not bad.any():
            return u2, v2
        u3, v3, rep = replace_invalid(u2, v2, min_neighbours=1, max_iter=1)
        if not rep.any():
            break
        u2, v2 = u3, v3
    bad = ~(np.isfinite(u2) & np.isfinite(v2))
    if bad.any():
        good = ~bad
        u2[bad] = np.median(u2[good]) if good.any() else 0.0
        v2[bad] = np.median(v2[good]) if good.any() else 0.0
    return u2, v2
