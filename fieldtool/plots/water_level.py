"""PNG of the water level on the cross-section; for the DEM method also the DEM and bed profiles and
D(x) = |DEM - bed| with its minima, their mean and the chosen divergence point (thesis figure 5.2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fieldtool.plots.discharge import _figure, _save
from fieldtool.processing.cross_section import CrossSection
from fieldtool.processing.water_level import LevelResult


def _section_axes(ax, cs: CrossSection, result: LevelResult) -> None:
    s, z = cs.station, cs.elevation
    lv, sig = result.level_m, result.uncertainty_m
    ss, depth = cs.wet_polyline(lv)
    ax.fill_between(ss, lv - depth, np.where(depth > 0, lv, lv - depth), color="#9ecae1", lw=0, label="water")
    ax.fill_between(s, z, z.min() - 0.1 * (np.ptp(z) + 1e-9), color="#d9c7a7", lw=0)
    ax.plot(s, z, "-", color="#6b4f2a", lw=1.5, label="bed (survey)")
    ax.axhline(lv, color="#08519c", lw=1.2, label=f"level {lv:.3f} ± {sig:.3f} m")
    ax.axhspan(lv - sig, lv + sig, color="#08519c", alpha=0.15, lw=0)
    left, right = result.details.get("water_edges_m", [None, None])
    if left is not None:
        ax.plot([left, right], [lv, lv], "o", color="#08519c", ms=5)
        ax.annotate("", xy=(right, lv), xytext=(left, lv), arrowprops={"arrowstyle": "<->", "color": "#08519c"})
        ax.text(0.5 * (left + right), lv, f"  {result.width_m:.3f} m", va="bottom", ha="center", color="#08519c")
    ax.set_xlabel("station (m, left bank -> right bank)")
    ax.set_ylabel("elevation (m)")
    ax.grid(alpha=0.3)


def plot_level(path, cs: CrossSection, result: LevelResult, dem_profile: dict | None = None) -> Path:
    """Write a PNG of the cross-section with the water level (and, for the DEM method, the profiles and
    D(x) as thesis figure 5.2). ``dem_profile`` defaults to ``result.details["dem_profile"]``.
    Returns the path written."""
    path = Path(path)
    prof = dem_profile if dem_profile is not None else result.details.get("dem_profile")
    fig = _figure(figsize=(8, 7.5 if prof else 4.5), dpi=110)
    title = {
        "value": "typed value",
        "width": "measured width",
        "dem": "adapted Hellebaut (DEM)",
        "angle_height": "angle and height",
        "image": "image method",
    }.get(result.method, result.method)
    if prof:
        ax0, ax1, ax2 = fig.subplots(3, 1, gridspec_kw={"height_ratios": [1.2, 1, 1], "hspace": 0.4})
    else:
        ax0 = fig.subplots(1, 1)
    _section_axes(ax0, cs, result)
    ax0.set_title(f"Water level — {title}: {result.level_m:.3f} m, width {result.width_m:.3f} m", y=1.0)
    ax0.legend(loc="lower right", fontsize=8)
    if prof:
        st = np.asarray(prof["station_m"])
        s_div = prof["divergence_station_m"]
        ax1.plot(st, prof["bed_m"], "-", color="#6b4f2a", label="bed (survey)")
        ax1.plot(st, prof["dem_m"], "-", color="#31a354", lw=0.8, label="DEM")
        ax1.axvline(s_div, color="r", lw=1, label=f"divergence {s_div:.3f} m")
        ax1.axhline(result.level_m, color="#08519c", lw=1)
        ax1.set_ylabel("elevation (m)")
        ax1.legend(fontsize=8)
        ax1.grid(alpha=0.3)
        ax2.plot(st, prof["d_m"], "-", color="0.4", lw=0.8, label="D(x) = |DEM - bed|")
        ax2.plot(prof["minima_station_m"], prof["minima_d_m"], "k.", ms=4, label="minima")
        ax2.axhline(prof["threshold_m"], color="r", lw=1, label=f"mean of minima {prof['threshold_m']:.3f} m")
        d_auto = float(np.interp(prof["auto_station_m"], st, prof["d_m"]))
        ax2.plot([prof["auto_station_m"]], [d_auto], "o", color="r", ms=7, label="chosen minimum")
        if abs(s_div - prof["auto_station_m"]) > 1e-9:
            ax2.axvline(s_div, color="m", ls="--", lw=1, label="user's divergence point")
        ax2.set_xlabel("station (m)")
        ax2.set_ylabel("D (m)")
        ax2.legend(fontsize=8)
        ax2.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    return _save(fig, path)
