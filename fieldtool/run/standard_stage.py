"""The run's ISO 748 and IVE uncertainty (``uncertainty_standard`` of result.json), beside the Monte Carlo.

Thin glue: reads the run's subsections, per-pair fields and [uncertainty] keys and calls the pure
:mod:`fieldtool.processing.standard_uncertainty`.
"""

from __future__ import annotations

import numpy as np

from fieldtool.processing import discharge as dq
from fieldtool.processing import standard_uncertainty as su
from fieldtool.run.assess import sigmas


def exposure_s(res) -> float:
    """The analysed duration (s): first to last frame pair, plus one pair's interval."""
    t = np.asarray(getattr(res, "t_pairs", None) if getattr(res, "t_pairs", None) is not None else [], float)
    if len(t) == 0:
        return float("nan")
    dt = float(np.median(res.dt_s)) if getattr(res, "dt_s", None) is not None and len(res.dt_s) else 0.0
    return float(t.max() - t.min() + dt)


def pair_velocities(geom: dq.SectionGeometry, mapping, res) -> np.ndarray | None:
    """(n_pairs, n_sub) surface velocity of each subsection in each frame pair (m/s, NaN where none)."""
    if getattr(res, "u_pairs", None) is None or len(res.u_pairs) < 2:
        return None
    out = []
    for k in range(len(res.u_pairs)):
        U, V = mapping.rectify_velocity(res.x, res.y, res.u_pairs[k], res.v_pairs[k])
        out.append(dq.subsection_velocity(geom, res.x, res.y, U, V))
    return np.asarray(out)


def standard_sigmas(project, level, mapping, dres, geom) -> su.StandardSigmas:
    """The standard methods' 1σ from the same [uncertainty] keys the Monte Carlo reads."""
    mc = sigmas(project, level)
    return su.StandardSigmas(
        piv_rel=max(mc.piv_rel, 0.0),
        filled_rel=mc.filled_rel,
        alpha_rel=mc.alpha / dres.alpha if dres.alpha > 0 else 0.0,
        rect_rel=float(mapping.residual_m or 0.0) / geom.length_m if geom.length_m > 0 else 0.0,
        level_m=mc.level_m,
        bed_m=mc.bed_m,
    )


def compute(project, level, mapping, geom, res, dres) -> dict:
    """``{"iso748": {...}, "ive": {...}, "k": 2}`` of a finished run."""
    edges = np.r_[dres.station_from, dres.station_to[-1:]]
    return su.standard_uncertainty(
        edges,
        dres.mean_depth_m,
        dres.surface_velocity_ms,
        dres.velocity_filled,
        dres.sub_discharge_m3s,
        exposure_s(res),
        standard_sigmas(project, level, mapping, dres, geom),
        velocity_pairs=pair_velocities(geom, mapping, res),
    )
