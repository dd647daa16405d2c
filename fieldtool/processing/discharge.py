"""Discharge from a surface velocity field, a section of interest, the cross-section and the level.

Thesis chapter 8, with two changes a hydrologist expects:
- the velocity of a subsection is the mean normal component sampled at several points along the
  subsection (interpolated from the field), not only the nearest vector: far from the camera one
  window covers metres;
- a subsection without valid vectors gets the velocity of the nearest valid one carried along the local
  Manning law v ∝ depth^(2/3): scaled by its depth-weighted mean of depth^(2/3) (as the discharge weighs it)
  over the neighbour's plain mean (as its sample points average it), and is flagged in the table;
- a sample point whose window (centred on it, final pass) reaches over a water edge (a bank or an
  island) is left out (``footprint_px``): stationary removal blanks the bank, so such a window reads
  the faster water beside it, +50 % at an edge subsection of the oblique scene. A subsection left with
  no sample is filled as above. When fewer than half of the subsections would keep a sample (a narrow
  stream under large windows), every sample is kept and the run says so.

Section of interest: two points, P1 the left water edge and P2 the right water edge (left/right
looking downstream). Subsection i spans the fraction [i/n, (i+1)/n] of P1->P2; its stations on the
cross-section run from the left water edge to the right one (or from ``station_offset_m`` by the
metric distance along the section, when given). The downstream unit normal is the section direction
turned 90° counter-clockwise in the world plane (Z up). Q = Σ alpha · A_i · v_i (m³/s).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fieldtool.errors import GeometryError, ParameterError
from fieldtool.processing.cross_section import CrossSection
from fieldtool.processing.ortho import OrthoMapping, check_in_frame

SAMPLES_PER_SUB = 7


def default_alpha(mean_depth_m: float) -> float:
    """Velocity index of the thesis (Hauet): 0.8 for a mean depth below 2 m, 0.9 above."""
    return 0.8 if mean_depth_m < 2.0 else 0.9


@dataclass
class SectionGeometry:
    """Section of interest in the image and on the water plane."""

    p_img: np.ndarray  # (2, 2) px, P1 then P2
    p_world: np.ndarray  # (2, 2) m
    length_m: float
    normal: np.ndarray  # (2,) downstream unit normal, world
    station_edges: np.ndarray  # (n+1,) stations of the subsection limits (m)
    sample_img: np.ndarray  # (n, k, 2) px sample points along each subsection
    swapped: bool = False  # P1/P2 were swapped because the flow ran upstream of the normal
    trusted: np.ndarray | None = None  # (n, k) bool: the sample's windows lie on water (None = all)
    edge_note: str = ""  # why edge samples were kept or dropped, for the run's warnings


def window_reach_px(window_px: int) -> float:
    """How far (px) from a point the final-pass window centred on it reaches: half a window. (The bilinear
    interpolation also reads neighbours up to one node spacing away, with weights that fall to zero there;
    counting them too dropped subsections that read within 0.7 % of the truth on the oblique scene.)"""
    return 0.5 * window_px


def section_geometry(
    points_px,
    mapping: OrthoMapping,
    cs: CrossSection,
    level: float,
    n_sub: int,
    station_offset_m: float | None = None,
    image_shape: tuple[int, int] | None = None,
    footprint_px: float = 0.0,
) -> SectionGeometry:
    """Build the section of interest (see module docstring).

    ``footprint_px``: how far (px, image axes) from a sample point the window centred on it reaches
    (:func:`window_reach_px`); 0 keeps every sample.
    """
    p = np.asarray(points_px, float)
    if p.shape != (2, 2):
        raise ParameterError("section.points_px: give two [x, y] pixel points, the left then the right water edge")
    check_in_frame(p, image_shape, "section.points_px")
    if n_sub < 1:
        raise ParameterError(f"section.n_sub: {n_sub} subsections is not possible; use 1 or more (15 is typical)")
    pw = mapping.image_to_world(p)
    d = pw[1] - pw[0]
    length = float(np.hypot(*d))
    if length <= 0:
        raise GeometryError("section.points_px: the two points coincide")
    t = d / length
    normal = np.array([-t[1], t[0]])
    if station_offset_m is None:
        left, right = cs.water_edges(level)
        edges = np.linspace(left, right, n_sub + 1)
    else:
        edges = station_offset_m + np.linspace(0.0, length, n_sub + 1)
    frac = (np.arange(n_sub)[:, None] + (np.arange(SAMPLES_PER_SUB)[None, :] + 0.5) / SAMPLES_PER_SUB) / n_sub
    pts_w = pw[0] + frac[..., None] * d
    sample_img = mapping.world_to_image(pts_w.reshape(-1, 2)).reshape(n_sub, SAMPLES_PER_SUB, 2)
    geom = SectionGeometry(p, pw, length, normal, edges, sample_img)
    if footprint_px > 0:
        geom.trusted, geom.edge_note = _on_water(geom, frac, mapping, cs, level, float(footprint_px))
    return geom


def _on_water(
    geom: SectionGeometry, frac: np.ndarray, mapping: OrthoMapping, cs: CrossSection, level: float, footprint_px: float
) -> tuple[np.ndarray, str]:
    """(n, k) bool: the stations within the windows' reach of each sample point are all wet.

    The reach (m along the section) is the largest projection on the section of the square of half-side
    ``footprint_px`` around the sample, mapped to the water plane.
    """
    n, k, _ = geom.sample_img.shape
    pts = geom.sample_img.reshape(-1, 2)
    t = (geom.p_world[1] - geom.p_world[0]) / geom.length_m
    centre = mapping.image_to_world(pts)
    reach = np.zeros(len(pts))
    for dx, dy in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
        corner = mapping.image_to_world(pts + footprint_px * np.array([dx, dy], float))
        reach = np.fmax(reach, np.abs((corner - centre) @ t))
    span = geom.station_edges[-1] - geom.station_edges[0]
    stations = geom.station_edges[0] + frac.reshape(-1) * span
    reach = reach * (span / geom.length_m)
    ok = np.isfinite(reach)
    reach = np.where(ok, reach, 0.0)
    for f in np.linspace(-1.0, 1.0, 9):
        ok &= cs.depth_at(level, stations + f * reach) > 0
    ok = ok.reshape(n, k)
    kept = ok.any(axis=1)
    if not kept.all() and kept.mean() < 0.5:
        return np.ones((n, k), bool), (
            f"the interrogation windows reach over a water edge in {int((~kept).sum())} of "
            f"{n} subsections; all samples kept (smaller piv.window_px would avoid it)"
        )
    return ok, ""


def section_samples(geom: SectionGeometry, x, y, U, V) -> np.ndarray:
    """Downstream-normal velocity (m/s) at each subsection's sample points, (n, k); NaN where invalid or
    where the sample's windows reach over a water edge."""
    su, sv = sample_field(x, y, U, V, geom.sample_img)
    vn = su * geom.normal[0] + sv * geom.normal[1]
    return vn if geom.trusted is None else np.where(geom.trusted, vn, np.nan)


def bilinear_cells(x: np.ndarray, y: np.ndarray, pts: np.ndarray):
    """The grid cell of each point for bilinear interpolation on the regular grid of node centres ``x``, ``y``
    (ny, nx) px: ``inside`` (pts.shape[:-1]) bool, the points within the grid; for those, in order, the cell's
    first column and row ``i0``, ``j0`` and the fractions ``ax``, ``ay`` (0..1) towards the next node."""
    xs, ys = x[0, :], y[:, 0]
    nx, ny = len(xs), len(ys)
    px, py = pts[..., 0], pts[..., 1]
    fx = np.interp(px, xs, np.arange(nx), left=np.nan, right=np.nan) if nx > 1 else np.zeros_like(px)
    fy = np.interp(py, ys, np.arange(ny), left=np.nan, right=np.nan) if ny > 1 else np.zeros_like(py)
    inside = np.isfinite(fx) & np.isfinite(fy)
    fx_i, fy_i = fx[inside], fy[inside]
    i0 = np.clip(np.floor(fx_i).astype(int), 0, max(nx - 2, 0))
    j0 = np.clip(np.floor(fy_i).astype(int), 0, max(ny - 2, 0))
    return inside, i0, j0, fx_i - i0, fy_i - j0


def sample_field(
    x: np.ndarray, y: np.ndarray, U: np.ndarray, V: np.ndarray, pts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation of a world-velocity field given on a regular pixel grid.

    ``x``, ``y`` (ny, nx) node centres (px), ``U``, ``V`` (ny, nx) m/s with NaN for invalid nodes;
    ``pts`` (..., 2) px. Invalid neighbours are left out and the weights renormalised
    (normalised convolution); a point with no valid neighbour, or outside the grid, gives NaN.
    ``U``, ``V`` may also be (n, ny, nx), n fields on the same grid, with ``pts`` (n, ..., 2): field i is
    sampled at ``pts[i]``.
    """
    ny, nx = U.shape[-2:]
    px = pts[..., 0]
    row0 = np.zeros(px.shape, int)  # the first row of each point's field in the stacked (n * ny, nx) grid
    if U.ndim == 3:
        row0 = row0 + (np.arange(len(U)) * ny).reshape((-1,) + (1,) * (px.ndim - 1))
        U, V = U.reshape(-1, nx), V.reshape(-1, nx)
    out_u = np.full(px.shape, np.nan)
    out_v = np.full(px.shape, np.nan)
    inside, i0, j0, ax, ay = bilinear_cells(x, y, pts)
    r0 = row0[inside]
    acc_u = np.zeros(len(ax))
    acc_v = np.zeros(len(ax))
    acc_w = np.zeros(len(ax))
    for dj, wy in ((0, 1 - ay), (1, ay)):
        for di, wx in ((0, 1 - ax), (1, ax)):
            jj = r0 + np.minimum(j0 + dj, ny - 1)
            ii = np.minimum(i0 + di, nx - 1)
            uu, vv = U[jj, ii], V[jj, ii]
            ok = np.isfinite(uu) & np.isfinite(vv)
            wgt = np.where(ok, wx * wy, 0.0)
            acc_u += np.where(ok, uu, 0.0) * wgt
            acc_v += np.where(ok, vv, 0.0) * wgt
            acc_w += wgt
    good = acc_w > 1e-6
    ru = np.full(len(ax), np.nan)
    rv = np.full(len(ax), np.nan)
    ru[good] = acc_u[good] / acc_w[good]
    rv[good] = acc_v[good] / acc_w[good]
    out_u[inside], out_v[inside] = ru, rv
    return out_u, out_v


@dataclass
class DischargeResult:
    """Discharge and its subsection table. Units: m, m², m/s, m³/s."""

    discharge_m3s: float
    alpha: float
    alpha_default: bool
    water_level_m: float
    wetted_area_m2: float  # area between the section's first and last station
    wetted_width_m: float
    mean_velocity_ms: float  # Q / area (depth-averaged)
    section_length_m: float
    station_from: np.ndarray
    station_to: np.ndarray
    area_m2: np.ndarray
    mean_depth_m: np.ndarray
    surface_velocity_ms: np.ndarray  # normal component, downstream positive
    velocity_filled: np.ndarray  # True where the velocity came from a neighbour
    sub_discharge_m3s: np.ndarray
    warnings: list[str] = field(default_factory=list)
    velocities: str = "piv"  # whose surface velocities: piv | stiv | combined (section.velocity_source)


def subsection_velocity(geom: SectionGeometry, x, y, U, V) -> np.ndarray:
    """Mean downstream-normal surface velocity (m/s) per subsection; NaN where nothing is valid."""
    vn = section_samples(geom, x, y, U, V)
    with np.errstate(invalid="ignore"):
        cnt = np.sum(np.isfinite(vn), axis=1)
        return np.where(cnt > 0, np.nansum(vn, axis=1) / np.maximum(cnt, 1), np.nan)


def manning_factors(cs: CrossSection, level: float, edges: np.ndarray, k: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The local Manning law v ∝ depth^(2/3) averaged two ways over each subsection between ``edges`` (m):
    weighted by depth, as the discharge weighs a surface velocity (``to``), and plain, as the sample points
    along a subsection average the surface velocity (``frm``); m^(2/3), ``k`` points per subsection."""
    e = np.asarray(edges, float)
    s = e[:-1, None] + (np.arange(k)[None, :] + 0.5) / k * np.diff(e)[:, None]
    d = cs.depth_at(level, s)
    d23 = d ** (2.0 / 3.0)
    dsum = d.sum(axis=1)
    to = np.where(dsum > 0, (d23 * d).sum(axis=1) / np.where(dsum > 0, dsum, 1.0), 0.0)
    return to, d23.mean(axis=1)


def fill_velocity(v: np.ndarray, law: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Fill NaN subsection velocities from the nearest valid one along the local Manning law:
    v_i = v_j · to_i / frm_j with ``law = (to, frm)`` of :func:`manning_factors` (m/s); of two valid ones
    equally near, the left one. ``v`` may be (n, n_sub), n draws at once, with ``to``, ``frm`` of the same
    shape; a row with nothing valid stays NaN."""
    to, frm = (np.broadcast_to(np.asarray(a, float), np.shape(v)) for a in law)
    v = np.array(v, float)
    filled = ~np.isfinite(v)
    if not filled.any():
        return v, filled
    idx = np.broadcast_to(np.arange(v.shape[-1]), v.shape)
    prev = np.maximum.accumulate(np.where(filled, -1, idx), axis=-1)  # the nearest valid on the left, -1: none
    nxt = np.flip(np.minimum.accumulate(np.flip(np.where(filled, v.shape[-1], idx), -1), axis=-1), -1)
    use_prev = (prev >= 0) & ((nxt >= v.shape[-1]) | (idx - prev <= nxt - idx))
    j = np.where(use_prev, prev, nxt)
    some = (prev >= 0) | (nxt < v.shape[-1])
    jj = np.where(some, j, 0)
    vj = np.take_along_axis(v, jj, axis=-1)
    fj = np.take_along_axis(frm, jj, axis=-1)
    with np.errstate(all="ignore"):
        fill = np.where(fj > 0, vj * to / np.where(fj > 0, fj, 1.0), 0.0)
    v = np.where(filled & some, fill, v)
    return v, filled


def subsection_areas(geom: SectionGeometry, cs: CrossSection, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Wetted area (m²) and mean depth (m) of each subsection (trapezoidal rule on the cross-section)."""
    cs.check_level(level)
    edges = geom.station_edges
    area = np.array([cs.wetted_area(level, a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    widths = np.diff(edges)
    return area, np.where(widths > 0, area / np.where(widths > 0, widths, 1), 0.0)


def resolve_alpha(alpha: float | None, cs: CrossSection, level: float) -> float:
    """The velocity index given, or the thesis' default from the mean depth (area / width)."""
    if alpha is None:
        width = cs.wetted_width(level)
        alpha = default_alpha(cs.wetted_area(level) / width if width > 0 else 0.0)
    if not (0.0 < alpha <= 1.2):
        raise ParameterError(
            f"section.alpha: {alpha:g} is not a plausible velocity index; use 0.5 to 1.0 (0.85 typical)"
        )
    return float(alpha)


def pair_discharge(
    geom: SectionGeometry,
    area: np.ndarray,
    law: tuple[np.ndarray, np.ndarray],
    alpha: float,
    x: np.ndarray,
    y: np.ndarray,
    U: np.ndarray,
    V: np.ndarray,
) -> float:
    """Discharge (m³/s) of one velocity field (m/s on the pixel grid); NaN when nothing is valid.
    ``law``: :func:`manning_factors` of the section, for the fill."""
    v = subsection_velocity(geom, x, y, U, V)
    if not np.any(np.isfinite(v)):
        return float("nan")
    v, _ = fill_velocity(v, law)
    return float(np.sum(alpha * area * v))


def compute_discharge(
    geom: SectionGeometry, cs: CrossSection, level: float, surface_v: np.ndarray, alpha: float | None = None
) -> DischargeResult:
    """Q = Σ alpha · A_i · v_i over the subsections (trapezoidal areas on the cross-section)."""
    edges = geom.station_edges
    n = len(edges) - 1
    area, mean_depth = subsection_areas(geom, cs, level)
    warnings: list[str] = []
    if not np.any(np.isfinite(surface_v)):
        raise GeometryError(
            "section: no valid velocity vector on the section of interest; check section.points_px lies on the "
            "water inside the ROI and that the PIV found motion (window size, seeding, filters)"
        )
    v, filled = fill_velocity(surface_v, manning_factors(cs, level, edges))
    edge = filled & (~geom.trusted.any(axis=1) if geom.trusted is not None else False)
    if edge.any():
        warnings.append(
            f"{int(edge.sum())} of {n} subsections lie within the interrogation windows' reach of a water "
            "edge (the windows would read the faster water beside the bank): their velocity is the "
            "neighbour's carried along the local Manning law (v ∝ depth^(2/3))"
        )
    if (filled & ~edge).any():
        warnings.append(
            f"{int((filled & ~edge).sum())} of {n} subsections had no valid vector and were filled from a neighbour"
        )
    if geom.edge_note:
        warnings.append(geom.edge_note)
    total_area = float(area.sum())
    width = cs.wetted_width(level)
    alpha_default = alpha is None
    alpha = resolve_alpha(alpha, cs, level)
    q_sub = alpha * area * v
    Q = float(q_sub.sum())
    return DischargeResult(
        discharge_m3s=Q,
        alpha=float(alpha),
        alpha_default=alpha_default,
        water_level_m=float(level),
        wetted_area_m2=total_area,
        wetted_width_m=float(width),
        mean_velocity_ms=Q / total_area if total_area > 0 else float("nan"),
        section_length_m=geom.length_m,
        station_from=edges[:-1],
        station_to=edges[1:],
        area_m2=area,
        mean_depth_m=mean_depth,
        surface_velocity_ms=v,
        velocity_filled=filled,
        sub_discharge_m3s=q_sub,
        warnings=warnings,
    )


def check_section(
    geom: SectionGeometry,
    cs: CrossSection,
    level: float,
    min_length_fraction: float = 0.5,
    edge_tolerance_m: float | None = None,
) -> None:
    """GeometryError, with the measured numbers, unless the section spans the water at ``level``.

    The section's length on the water plane (from the ortho mapping) is compared with the wetted width of
    the cross-section: shorter than ``min_length_fraction`` of it (a double click) is refused; and its ends
    must land within ``edge_tolerance_m`` (m; None = 10 % of the wetted width, at least 0.3 m) of the water
    edges (stations from ``station_offset_m`` when given, else the left and right water edges); a section
    reaching further crosses a bank.
    """
    left, right = cs.water_edges(level)
    width = right - left
    L = geom.length_m
    if L < min_length_fraction * width:
        raise GeometryError(
            f"section.points_px: the section is {L:.2f} m long on the water but the river is {width:.2f} m wide at "
            f"level {level:.3f} m ({100 * L / width:.0f} %, less than section.min_length_fraction = "
            f"{min_length_fraction:g}); pick P1 on the left water edge and P2 on the right one"
        )
    tol = max(0.3, 0.1 * width) if edge_tolerance_m is None else float(edge_tolerance_m)
    s0, s1 = float(geom.station_edges[0]), float(geom.station_edges[-1])
    if abs(s1 - s0 - L) > 1e-6:  # stations run from edge to edge: compare the length with the width
        off = L - width
        if abs(off) > tol:
            where = "reaches beyond the water edges over a bank" if off > 0 else "stops short of the water edges"
            raise GeometryError(
                f"section.points_px: the section is {L:.2f} m long but the water is {width:.2f} m wide at level "
                f"{level:.3f} m: it {where} by {abs(off):.2f} m (tolerance {tol:.2f} m, section.edge_tolerance_m); "
                "put P1 and P2 on the water edges"
            )
        return
    bad = [(name, s, e) for name, s, e in (("P1", s0, left), ("P2", s1, right)) if abs(s - e) > tol]
    over = s0 < left - tol or s1 > right + tol
    if bad:
        txt = "; ".join(f"{n} at station {s:.2f} m, water edge at {e:.2f} m" for n, s, e in bad)
        raise GeometryError(
            f"section: {txt} (tolerance {tol:.2f} m, section.edge_tolerance_m)"
            f"{' — the section crosses a bank' if over else ''}; "
            "check section.points_px and section.station_offset_m"
        )


def profile_band(d, piv, section, mapping) -> dict[str, np.ndarray]:
    """Per-subsection surface velocity (m/s) of the mean field, with the 2.5 / 97.5 % of the per-pair fields.

    ``d``: the run's discharge result; ``piv``: its PIV result (per-pair fields ``u_pairs``, ``v_pairs``, px/s);
    ``section``: its section geometry; ``mapping``: the ortho mapping. Returns station_m (subsection centres, m),
    velocity_ms, filled (bool), p025_ms / p975_ms (NaN where fewer than 3 pairs measured), n_pairs."""
    per_pair = []
    for k in range(len(piv.u_pairs)):
        U, V = mapping.rectify_velocity(piv.x, piv.y, piv.u_pairs[k], piv.v_pairs[k])
        per_pair.append(subsection_velocity(section, piv.x, piv.y, U, V))
    vp = np.array(per_pair) if per_pair else np.full((0, len(d.area_m2)), np.nan)
    n = np.sum(np.isfinite(vp), axis=0)
    lo, hi = np.full(vp.shape[1], np.nan), np.full(vp.shape[1], np.nan)
    some = n >= 3  # only those: a subsection no pair measured has no percentile (and NumPy would warn of it)
    if some.any():
        measured = np.where(np.isfinite(vp[:, some]), vp[:, some], np.nan)
        lo[some], hi[some] = np.nanpercentile(measured, [2.5, 97.5], axis=0)
    return {
        "station_m": 0.5 * (d.station_from + d.station_to),
        "velocity_ms": np.asarray(d.surface_velocity_ms),
        "filled": np.asarray(d.velocity_filled, bool),
        "p025_ms": lo,
        "p975_ms": hi,
        "n_pairs": n,
    }
