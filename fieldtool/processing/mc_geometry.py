"""The section's geometry for many Monte Carlo draws at once (pure numpy).

Each draw of :func:`fieldtool.processing.uncertainty.monte_carlo_discharge` moves the image -> water-plane
homography. What depends on it alone (the section's ends on the water plane, its normal, the sample points in
the image and the rectified velocities) is computed here for all draws in one pass, with the same formulas as
:func:`fieldtool.processing.discharge.section_geometry` and :meth:`OrthoMapping.rectify_velocity`. Units: px in
the image, m on the water plane, px/s and m/s for velocities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldtool.processing.discharge import SAMPLES_PER_SUB, bilinear_cells, sample_field
from fieldtool.processing.ortho import homography_jacobian


def apply_homographies(Hs: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Map points by one homography per draw: ``Hs`` (n, 3, 3), ``pts`` (n or 1, m, 2) -> (n, m, 2)."""
    p = np.asarray(pts, float)
    q = np.einsum("nij,nmj->nmi", Hs[:, :, :2], np.broadcast_to(p, (len(Hs),) + p.shape[1:])) + Hs[:, None, :, 2]
    with np.errstate(all="ignore"):
        return q[..., :2] / q[..., 2:3]


@dataclass
class SectionDraws:
    """The section under ``n`` homographies. ``ok`` (n,) is False where a draw's section degenerates."""

    length_m: np.ndarray  # (n,) m
    normal: np.ndarray  # (n, 2) downstream unit normal on the water plane
    sample_img: np.ndarray  # (n, n_sub, k, 2) px
    ok: np.ndarray  # (n,) bool


def section_draws(points_px: np.ndarray, Hs: np.ndarray, n_sub: int) -> SectionDraws:
    """Ends, normal and sample points of the section ``points_px`` (2, 2) px under each of ``Hs`` (n, 3, 3)."""
    pw = apply_homographies(Hs, np.asarray(points_px, float)[None])  # (n, 2, 2) m
    d = pw[:, 1] - pw[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = np.isfinite(length) & (length > 0)
    with np.errstate(all="ignore"):
        t = d / np.where(ok, length, 1.0)[:, None]
    normal = np.stack([-t[:, 1], t[:, 0]], axis=1)
    k = SAMPLES_PER_SUB
    frac = ((np.arange(n_sub)[:, None] + (np.arange(k)[None, :] + 0.5) / k) / n_sub).reshape(-1)
    pts_w = pw[:, None, 0] + frac[None, :, None] * d[:, None, :]  # (n, n_sub * k, 2) m
    sample = apply_homographies(np.linalg.inv(Hs), pts_w).reshape(len(Hs), n_sub, k, 2)
    return SectionDraws(length, normal, sample, ok & np.isfinite(sample).all(axis=(1, 2, 3)))


def rectify_draws(Hs: np.ndarray, x: np.ndarray, y: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Pixel velocities (px/s) at nodes ``x``, ``y`` (any shape, px) -> world velocities (m/s), (n, *shape)
    each, under each homography: :func:`ortho.homography_jacobian` applied per draw."""
    J = homography_jacobian(Hs.reshape((len(Hs),) + (1,) * np.ndim(x) + (3, 3)), x, y)
    return J[..., 0, 0] * u + J[..., 0, 1] * v, J[..., 1, 0] * u + J[..., 1, 1] * v


def sampled_nodes(x: np.ndarray, y: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(ny, nx) bool: the grid nodes that the bilinear sampling of :func:`discharge.sample_field` reads for
    the points ``pts`` (..., 2) px; the others need no rectification."""
    ny, nx = x.shape
    need = np.zeros(x.shape, bool)
    _, i0, j0, _, _ = bilinear_cells(x, y, pts)
    for dj in (0, 1):
        for di in (0, 1):
            need[np.minimum(j0 + dj, ny - 1), np.minimum(i0 + di, nx - 1)] = True
    return need


def rectify_sampled(Hs: np.ndarray, x, y, u, v, sec: SectionDraws) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rectify_draws` on the nodes the section's samples read (NaN elsewhere), (n, ny, nx) m/s each."""
    need = sampled_nodes(x, y, sec.sample_img[sec.ok])
    U, V = np.full((len(Hs),) + x.shape, np.nan), np.full((len(Hs),) + x.shape, np.nan)
    U[:, need], V[:, need] = rectify_draws(Hs, x[need], y[need], u[need], v[need])
    return U, V


def normal_samples(sec: SectionDraws, x, y, U: np.ndarray, V: np.ndarray, trusted: np.ndarray | None) -> np.ndarray:
    """Downstream-normal velocity (m/s) at each draw's sample points, (n, n_sub, k); NaN where invalid or
    untrusted (as :func:`fieldtool.processing.discharge.section_samples`)."""
    su, sv = sample_field(x, y, U, V, sec.sample_img)
    vn = su * sec.normal[:, 0, None, None] + sv * sec.normal[:, 1, None, None]
    return vn if trusted is None else np.where(trusted[None], vn, np.nan)


def _interp_rows(station: np.ndarray, elev: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Bed elevation (m) at stations ``s`` (n, ...) m, linear between the survey's ``station`` (m,) with one
    row of elevations per draw, ``elev`` (n, m); as ``np.interp``, held at the ends."""
    j = np.clip(np.searchsorted(station, s, side="right") - 1, 0, len(station) - 2)
    w = np.clip((s - station[j]) / (station[j + 1] - station[j]), 0.0, 1.0)
    rows = np.arange(len(elev)).reshape((-1,) + (1,) * (s.ndim - 1))
    return elev[rows, j] * (1.0 - w) + elev[rows, j + 1] * w


def _wet_integral(a: np.ndarray, b: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Exact integral (m²) of max(0, depth) over a segment of ``width`` (m) where the depth runs linearly from
    ``a`` to ``b`` (m, negative where dry)."""
    both = (a >= 0) & (b >= 0)
    with np.errstate(all="ignore"):
        part = np.where(a > 0, a, b) ** 2 / (2.0 * (np.abs(a) + np.abs(b)))
    return width * np.where(both, 0.5 * (a + b), np.where((a <= 0) & (b <= 0), 0.0, part))


@dataclass
class BedDraws:
    """Subsection areas and Manning factors of ``n`` draws of bed and level; ``ok`` False where a draw's level
    leaves the section (at or below the lowest bed point, or over a bank top)."""

    area_m2: np.ndarray  # (n, n_sub)
    law: tuple[np.ndarray, np.ndarray]  # Manning factors (to, frm), (n, n_sub) each, m^(2/3)
    ok: np.ndarray  # (n,) bool


def bed_draws(
    station: np.ndarray, elev: np.ndarray, level: np.ndarray, n_sub: int, edges: np.ndarray | None, k: int = 32
) -> BedDraws:
    """Areas and Manning factors of the subsections for bed elevations ``elev`` (n, m) m on the survey's
    ``station`` (m,) m at water levels ``level`` (n,) m: the exact integral of the piecewise-linear depth
    (as :meth:`CrossSection.wet_polyline` with the crossings inserted) and :func:`discharge.manning_factors`.

    ``edges`` (n, n_sub + 1) m are the subsections' limits; None divides the span between the water edges (the
    outermost dry-to-wet crossings, as :meth:`CrossSection.water_edges`) into ``n_sub`` equal parts.
    """
    st = np.asarray(station, float)
    d = level[:, None] - elev  # (n, m) depth at the survey points, negative where dry
    ok = np.isfinite(level) & (level > elev.min(axis=1)) & (level <= elev[:, 0]) & (level <= elev[:, -1])
    wet = d >= 1e-9
    ok &= wet.any(axis=1)
    if edges is None:
        rows = np.arange(len(d))
        first = np.clip(np.argmax(wet, axis=1), 1, len(st) - 1)
        last = np.clip(len(st) - 1 - np.argmax(wet[:, ::-1], axis=1), 0, len(st) - 2)
        with np.errstate(all="ignore"):
            a, b = d[rows, first - 1], d[rows, first]
            left = np.where(a < 0, st[first - 1] + a / (a - b) * (st[first] - st[first - 1]), st[first - 1])
            a, b = d[rows, last], d[rows, last + 1]
            right = np.where(b < 0, st[last] + a / (a - b) * (st[last + 1] - st[last]), st[last + 1])
        edges = left[:, None] + np.linspace(0.0, 1.0, n_sub + 1)[None, :] * (right - left)[:, None]
    e = np.clip(edges, st[0], st[-1])
    cum = np.concatenate([np.zeros((len(d), 1)), np.cumsum(_wet_integral(d[:, :-1], d[:, 1:], np.diff(st)), axis=1)], 1)
    j = np.clip(np.searchsorted(st, e, side="right") - 1, 0, len(st) - 2)
    rows = np.arange(len(d))[:, None]
    de = level[:, None] - _interp_rows(st, elev, e)
    area = np.diff(cum[rows, j] + _wet_integral(d[rows, j], de, e - st[j]), axis=1)
    s = e[:, :-1, None] + (np.arange(k)[None, None, :] + 0.5) / k * np.diff(e, axis=1)[:, :, None]
    depth = np.clip(level[:, None, None] - _interp_rows(st, elev, s), 0.0, None)
    d23 = depth ** (2.0 / 3.0)
    dsum = depth.sum(axis=2)
    to = np.where(dsum > 0, (d23 * depth).sum(axis=2) / np.where(dsum > 0, dsum, 1.0), 0.0)
    return BedDraws(area, (to, d23.mean(axis=2)), ok)
