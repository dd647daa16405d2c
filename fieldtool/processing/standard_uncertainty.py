"""The hydrologists' standard uncertainty of a velocity-area discharge: ISO 748:2007 and the IVE.

Pure numpy, beside the Monte Carlo budget of :mod:`fieldtool.processing.uncertainty`. USGS IVyTools reports
both for image velocimetry, at 2σ, and rates the measurement from the ISO result; we do the same so that a
hydrologist can compare our interval with the ones they know.

Each subsection of the section of interest is taken as one "vertical" of the mid-section method: its
centre station ``s_i`` (m), width ``b_i`` (m), mean depth ``d_i`` (m), surface velocity ``v_i`` (m/s) and
discharge ``q_i = alpha · b_i · d_i · v_i`` (m³/s), ``Q = Σ q_i``. Every relative uncertainty below is a
1σ fraction (0.01 = 1 %); the reported ones are expanded with ``k = 2`` (about 95 %).

ISO 748:2007 (velocity-area method; clause 9 and Annex E, "uncertainty in the velocity-area method")
-------------------------------------------------------------------------------------------------
(1)  u²(Q) = u_s² + u_m² + Σ_i q_i² [u_b,i² + u_d,i² + u_p,i² + u_c,i² + u_e,i²] / Q²
     (the combination of ISO 748:2007 Annex E; the random components of each vertical are weighted by
     its discharge, the systematic ``u_s`` and the number-of-verticals ``u_m`` apply to the whole Q).
(2)  u_m  = table of the number of verticals n (ISO 748:2007 Table E.6, 1σ): 5 -> 7.5 %, 10 -> 4.5 %,
     15 -> 3.0 %, 20 -> 2.5 %, 25 -> 2.0 %, 30 -> 1.5 %, 35 and more -> 1.0 %; linear between, 7.5 % below 5
     (as IVyTools interpolates it).
(3)  u_b,i = 0.5 % (width between verticals, taped or surveyed).
(4)  u_d,i = sqrt(u_dt,i² + (σ_bed / d_i)²), u_dt,i = 0.5 % for d_i > 0.3 m, else 1.5 % (sounding; ISO 748
     Annex E as IVyTools reads it), plus the surveyed bed's own 1σ ``σ_bed`` (m) when given.
(5)  u_p,i = 7 % : "number of points in the vertical"; here one surface point turned into a mean velocity by
     the velocity index, whose local scatter about the section's index IVyTools takes as 7 % (1σ).
(6)  u_c,i = piv_rel (1 %) for a measured subsection: the repeatability of the "current meter", here the
     surface-velocity estimate (ISO 748 Table E.5 gives about 1 % for a rated meter above 0.15 m/s);
     ``filled_rel`` (25 %) for a subsection whose velocity was carried from a neighbour.
(7)  u_e,i = std_t(v_i(t)) / (v_i · sqrt(n_e)),  n_e = max(1, T / τ): limited exposure time. ISO 748
     Table E.3 tabulates it for a current meter from the velocity and the exposure time ``T``; a video
     measures the whole analysed duration ``T`` (s) at every frame pair, so it is estimated from the
     spread of the per-pair subsection velocities, with one independent sample per ``τ`` = 1 s of
     turbulence (the largest eddies of a small river turn over in about a second). Without per-pair
     velocities: IVyTools' 8 %.
(8)  u_s = sqrt(u_sm² + u_so² + u_alpha² + u_rect² + u_level²): instrument (1 %), other sources (1 %),
     the section's velocity index (σ_alpha / alpha), the rectification (GCP residual / section length, as
     IVyTools) and the water level (σ_level · W / A: a level error shifts every depth the same way).

Interpolated Variance Estimator (Cohn, Kiang & Mason 2013, J. Hydraul. Eng. 139(5) 502-510)
------------------------------------------------------------------------------------------
The error of each vertical's depth and velocity is estimated from how far it departs from the linear
interpolation of its two neighbours (the flow varies smoothly; what does not is error):
(9)  ω_i = (s_{i+1} - s_i) / (s_{i+1} - s_{i-1}),   δx_i = x_i - [ω_i x_{i-1} + (1 - ω_i) x_{i+1}]
(10) E[δx_i²] = σ_x² (1 + ω_i² + (1 - ω_i)²) = 2 σ_x² (1 - ω_i + ω_i²)  (independent errors of equal σ_x)
(11) s_x² = (1 / m) Σ_i δx_i² / [2 (1 - ω_i + ω_i²)]  over the m interior verticals whose neighbours
     are both measured (x = d, depth, and x = v, surface velocity; filled velocities are left out of the
     velocity sum: they are interpolations, their residual says nothing of the error); s_v >= piv_rel · v̄.
(12) u²(Q) = u_s² + Σ_i q_i² [(s_d / d_i)² + (s_v / v_i)² + u_b²] / Q²  (the paper's total, its
     equation 17, with the systematic ``u_s`` of (8) added as IVyTools does; the paper's 1σ is reported
     here at 2σ, as IVyTools reports it). A filled vertical keeps max(s_v / v_i, filled_rel).

Rating (USGS; Turnipseed & Sauer 2010, Techniques and Methods 3-A8, and QRev's "User Rating"; IVyTools
offers the same list, e.g. "Good (3-5%)" in its guide): the expanded (2σ) relative uncertainty
<= 2 % excellent, <= 5 % good, <= 8 % fair, > 8 % poor.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

#: ISO 748:2007 Table E.6: number of verticals -> u_m (1σ fraction), as IVyTools tabulates it
ISO_VERTICALS = (
    np.array([5, 10, 15, 20, 25, 30, 35], float),
    np.array([0.075, 0.045, 0.030, 0.025, 0.020, 0.015, 0.010]),
)
#: expanded (2σ) relative uncertainty -> rating (upper bounds, inclusive)
RATINGS = ((0.02, "excellent"), (0.05, "good"), (0.08, "fair"))
K = 2.0  # coverage factor of the reported intervals


@dataclass
class StandardSigmas:
    """1σ inputs of the standard methods; fractions unless the name carries a unit."""

    u_b: float = 0.005  # width (3)
    u_p: float = 0.07  # one surface point and the velocity index, per vertical (5)
    piv_rel: float = 0.01  # repeatability of the surface-velocity estimate (6); floor of s_v (11)
    filled_rel: float = 0.25  # velocity carried from a neighbour (6), (12)
    u_e_default: float = 0.08  # exposure time without per-pair velocities (7)
    decorrelation_s: float = 1.0  # τ of (7), s
    u_sm: float = 0.01  # systematic, instrument (8)
    u_so: float = 0.01  # systematic, other sources (8)
    alpha_rel: float = 0.03  # velocity index σ_alpha / alpha (8)
    rect_rel: float = 0.0  # rectification: GCP residual / section length (8)
    level_m: float = 0.0  # water level σ (m) (8)
    bed_m: float = 0.0  # surveyed bed elevation σ (m) (4)


def rating(u95_rel: float | None) -> str | None:
    """USGS rating of an expanded (2σ) relative uncertainty; None when it is not known."""
    if u95_rel is None or not np.isfinite(u95_rel):
        return None
    for bound, name in RATINGS:
        if u95_rel <= bound:
            return name
    return "poor"


def u_verticals(n: int) -> float:
    """u_m (1σ fraction) of ``n`` verticals, equation (2)."""
    return float(np.interp(n, *ISO_VERTICALS))


def _interval(q: float, u: float) -> dict:
    """The reported block: 1σ and 2σ relative, the 2σ interval (m³/s) and the rating."""
    if not (np.isfinite(u) and np.isfinite(q)):
        return {"u_rel": None, "u95_rel": None, "ci95_m3s": None, "rating": None}
    u95 = K * u
    return {
        "u_rel": float(u),
        "u95_rel": float(u95),
        "ci95_m3s": [float(q - u95 * abs(q)), float(q + u95 * abs(q))],
        "rating": rating(u95),
    }


def _systematic(sig: StandardSigmas, width_m: float, area_m2: float) -> tuple[float, dict]:
    """u_s of equation (8) and its parts."""
    u_level = sig.level_m * width_m / area_m2 if area_m2 > 0 else 0.0
    parts = {
        "u_sm": sig.u_sm,
        "u_so": sig.u_so,
        "u_alpha": sig.alpha_rel,
        "u_rect": sig.rect_rel,
        "u_level": float(u_level),
    }
    return float(np.sqrt(sum(v * v for v in parts.values()))), parts


def _check(edges, depth, velocity, filled, q):
    e = np.asarray(edges, float)
    d = np.asarray(depth, float)
    v = np.asarray(velocity, float)
    f = np.zeros(len(d), bool) if filled is None else np.asarray(filled, bool)
    qq = np.asarray(q, float)
    n = len(d)
    if e.shape != (n + 1,) or v.shape != (n,) or f.shape != (n,) or qq.shape != (n,):
        raise ValueError("standard uncertainty: station_edges needs n+1 values and depth, velocity, filled, q n each")
    return e, d, v, f, qq


def exposure_u(velocity_pairs, velocity, exposure_s: float, sig: StandardSigmas) -> np.ndarray:
    """u_e,i of equation (7) per subsection (fraction). ``velocity_pairs`` (n_pairs, n) m/s or None."""
    v = np.asarray(velocity, float)
    if velocity_pairs is None:
        return np.full(len(v), sig.u_e_default)
    vp = np.asarray(velocity_pairs, float)
    n_e = max(1.0, float(exposure_s) / sig.decorrelation_s) if np.isfinite(exposure_s) else 1.0
    cnt = np.sum(np.isfinite(vp), axis=0)
    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)  # a column with fewer than two values gives NaN
        sd = np.where(cnt >= 2, np.nanstd(vp, axis=0, ddof=1), np.nan)
        u = sd / (np.abs(v) * np.sqrt(np.minimum(n_e, np.maximum(cnt, 1))))
    return np.where(np.isfinite(u), u, sig.u_e_default)


def iso748(
    station_edges, depth, velocity, filled, q, exposure_s: float, sig: StandardSigmas | None = None, velocity_pairs=None
) -> dict:
    """ISO 748:2007 uncertainty of Q (equation (1)); see the module docstring.

    Parameters
    ----------
    station_edges : (n+1,) m, subsection limits.   depth : (n,) m, mean depth of each subsection.
    velocity : (n,) m/s, surface velocity.   filled : (n,) bool, velocity carried from a neighbour.
    q : (n,) m³/s, subsection discharge.   exposure_s : s, the analysed duration of the clip.
    velocity_pairs : (n_pairs, n) m/s, the subsection velocity of each frame pair, or None.

    Returns the ``iso748`` block of result.json: ``u_rel`` (1σ), ``u95_rel`` (2σ), ``ci95_m3s``, ``rating``
    and ``components`` (each 1σ fraction of Q).
    """
    sig = sig or StandardSigmas()
    e, d, v, f, qq = _check(station_edges, depth, velocity, filled, q)
    Q = float(qq.sum())
    b = np.diff(e)
    area = float(np.sum(b * d))
    u_s, sys_parts = _systematic(sig, float(e[-1] - e[0]), area)
    u_m = u_verticals(len(d))
    with np.errstate(invalid="ignore", divide="ignore"):
        u_dt = np.where(d > 0.3, 0.005, 0.015)
        u_d = np.sqrt(u_dt**2 + np.where(d > 0, sig.bed_m / np.where(d > 0, d, 1.0), 0.0) ** 2)
    u_b = np.full(len(d), sig.u_b)
    u_p = np.full(len(d), sig.u_p)
    u_c = np.where(f, sig.filled_rel, sig.piv_rel)
    u_e = exposure_u(velocity_pairs, v, exposure_s, sig)
    w = (qq / Q) ** 2 if Q != 0 else np.full(len(qq), np.nan)
    comp = {
        name: float(np.sqrt(np.sum(w * c**2)))
        for name, c in (("u_b", u_b), ("u_d", u_d), ("u_p", u_p), ("u_c", u_c), ("u_e", u_e))
    }
    u2 = u_s**2 + u_m**2 + sum(c**2 for c in comp.values())
    out = _interval(Q, float(np.sqrt(u2)))
    out["components"] = {"u_s": u_s, "u_m": u_m, **comp, **sys_parts}
    out["n_verticals"] = len(d)
    out["exposure_s"] = float(exposure_s) if np.isfinite(exposure_s) else None
    return out


def interpolation_sd(stations, x, use=None) -> tuple[float, int]:
    """s_x of equation (11) and the number m of residuals it used; (nan, 0) with none.

    ``stations`` (n,) m (the verticals' stations), ``x`` (n,) the depths or velocities, ``use`` (n,) bool:
    the values that are measurements (default all finite)."""
    s = np.asarray(stations, float)
    x = np.asarray(x, float)
    ok = np.isfinite(x) if use is None else (np.asarray(use, bool) & np.isfinite(x))
    terms = []
    for i in range(1, len(x) - 1):
        if not (ok[i - 1] and ok[i] and ok[i + 1]):
            continue
        span = s[i + 1] - s[i - 1]
        if span <= 0:
            continue
        om = (s[i + 1] - s[i]) / span
        delta = x[i] - (om * x[i - 1] + (1.0 - om) * x[i + 1])
        terms.append(delta**2 / (2.0 * (1.0 - om + om**2)))
    if not terms:
        return float("nan"), 0
    return float(np.sqrt(np.mean(terms))), len(terms)


def ive(station_edges, depth, velocity, filled, q, sig: StandardSigmas | None = None) -> dict:
    """Interpolated Variance Estimator of Q (equations (9)-(12)); the same inputs and block as :func:`iso748`
    (no exposure time: the IVE reads the velocities' roughness across the section instead)."""
    sig = sig or StandardSigmas()
    e, d, v, f, qq = _check(station_edges, depth, velocity, filled, q)
    Q = float(qq.sum())
    st = 0.5 * (e[:-1] + e[1:])
    s_d, m_d = interpolation_sd(st, d, d > 0)
    s_v, m_v = interpolation_sd(st, v, ~f)
    vbar = float(np.nanmean(np.abs(v[~f]))) if (~f).any() else float("nan")
    floor_v = sig.piv_rel * vbar if np.isfinite(vbar) else 0.0
    s_d = 0.0 if not np.isfinite(s_d) else s_d
    s_v = floor_v if not np.isfinite(s_v) else max(s_v, floor_v)
    u_s, sys_parts = _systematic(sig, float(e[-1] - e[0]), float(np.sum(np.diff(e) * d)))
    with np.errstate(invalid="ignore", divide="ignore"):
        rd = np.where(d > 0, s_d / np.where(d > 0, d, 1.0), 0.0)
        rv = np.where(np.abs(v) > 0, s_v / np.where(np.abs(v) > 0, np.abs(v), 1.0), 0.0)
    rv = np.where(f, np.maximum(rv, sig.filled_rel), rv)
    w = (qq / Q) ** 2 if Q != 0 else np.full(len(qq), np.nan)
    comp = {
        "u_d": float(np.sqrt(np.sum(w * rd**2))),
        "u_v": float(np.sqrt(np.sum(w * rv**2))),
        "u_b": float(np.sqrt(np.sum(w * sig.u_b**2))),
    }
    u2 = u_s**2 + sum(c**2 for c in comp.values())
    out = _interval(Q, float(np.sqrt(u2)))
    out["components"] = {"u_s": u_s, **comp, **sys_parts}
    out["s_depth_m"] = float(s_d)
    out["s_velocity_ms"] = float(s_v)
    out["n_residuals"] = {"depth": m_d, "velocity": m_v}
    return out


def standard_uncertainty(
    station_edges, depth, velocity, filled, q, exposure_s: float, sig: StandardSigmas | None = None, velocity_pairs=None
) -> dict:
    """``{"iso748": ..., "ive": ...}``: the ``uncertainty_standard`` block of result.json."""
    return {
        "iso748": iso748(station_edges, depth, velocity, filled, q, exposure_s, sig, velocity_pairs),
        "ive": ive(station_edges, depth, velocity, filled, q, sig),
        "k": K,
    }
