"""A clip in which nothing could be measured on the section: an unusable verdict, not an input error (issue 23).

A dark, blank or glare-filled clip is not bad input: exit 2 is for inputs the user must fix; this is exit 3, a
measurement judged unusable, with every result file written and ``discharge_m3s`` null. :func:`verdict` gives
the discharge table (areas and depths as surveyed, velocities and discharges NaN) and the quality.
"""

from __future__ import annotations

import numpy as np

from fieldtool.processing import discharge as dq
from fieldtool.processing.quality import Quality, Reason


def nothing_measured(v_sub: np.ndarray) -> bool:
    """True when no subsection of the section has a finite velocity (m/s)."""
    return not np.any(np.isfinite(np.asarray(v_sub, float)))


def verdict(
    geom: dq.SectionGeometry, cs, level_m: float, alpha: float | None, facts: dict | None = None
) -> tuple[dq.DischargeResult, Quality]:
    """The discharge table of an unmeasured section (NaN velocities and discharge) and its unusable quality.
    ``facts``: the clip's estimates (``robust`` of result.json), quoted in the reason when present."""
    edges = geom.station_edges
    n = len(edges) - 1
    area, mean_depth = dq.subsection_areas(geom, cs, level_m)
    alpha_default = alpha is None
    a = dq.resolve_alpha(alpha, cs, level_m)
    nan = np.full(n, np.nan)
    dres = dq.DischargeResult(
        discharge_m3s=float("nan"),
        alpha=a,
        alpha_default=alpha_default,
        water_level_m=float(level_m),
        wetted_area_m2=float(area.sum()),
        wetted_width_m=float(cs.wetted_width(level_m)),
        mean_velocity_ms=float("nan"),
        section_length_m=geom.length_m,
        station_from=edges[:-1],
        station_to=edges[1:],
        area_m2=area,
        mean_depth_m=mean_depth,
        surface_velocity_ms=nan.copy(),
        velocity_filled=np.ones(n, bool),
        sub_discharge_m3s=nan.copy(),
        warnings=[],
    )
    msg = (
        "no valid velocity vector on the section: nothing could be measured (check that section.points_px lies on "
        "the water inside the ROI; dark, blank or glare-covered water gives no motion to correlate)"
    )
    c = (facts or {}).get("contrast") or {}
    nz = (facts or {}).get("noise") or {}
    if c.get("tracer_gray") is not None and nz.get("temporal_sd_gray") is not None:
        msg += (
            f"; the clip's tracers stand {c['tracer_gray']:.1f} grey levels above the water, "
            f"{c['cnr']:.2f} x its noise of {nz['temporal_sd_gray']:.2f}"
        )
    return dres, Quality("unusable", [Reason("nothing_measured", "unusable", msg, 0.0, None)])
