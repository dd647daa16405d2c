"""Figures for the report, drawn at the end of a run: the surface-velocity profile along the section
with its band, and the GCPs on the first frame with their distances and residuals.

Profile band: the subsection velocity is computed on every per-pair field the run kept; the band is
the 2.5-97.5 % range of those per-pair values (how much one pair's field varies, not the
uncertainty of the mean, which is narrower). Written to ``section_profile.csv`` too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fieldtool.plots.discharge import _figure, _save, _show, _working_rgb
from fieldtool.processing import discharge as dq
from fieldtool.processing.ortho import NAMES, PAIRS
from fieldtool.project.model import atomic_write_bytes


def write_profile(out: Path, result) -> tuple[str, str]:
    """``section_profile.csv`` and ``profile.png``; returns their names."""
    b = dq.profile_band(result.discharge, result.piv, result.section, result.mapping)
    rows = ["station_m,surface_velocity_ms,velocity_filled,pairs_p025_ms,pairs_p975_ms,n_pairs"]
    for i in range(len(b["station_m"])):
        f = [
            f"{b['station_m'][i]:.4f}",
            f"{b['velocity_ms'][i]:.5f}",
            str(int(b["filled"][i])),
            "" if not np.isfinite(b["p025_ms"][i]) else f"{b['p025_ms'][i]:.5f}",
            "" if not np.isfinite(b["p975_ms"][i]) else f"{b['p975_ms'][i]:.5f}",
            str(int(b["n_pairs"][i])),
        ]
        rows.append(",".join(f))
    atomic_write_bytes(out / "section_profile.csv", ("\n".join(rows) + "\n").encode())

    fig = _figure(figsize=(9, 4.2))
    ax = fig.subplots()
    s, v = b["station_m"], b["velocity_ms"]
    band = np.isfinite(b["p025_ms"]) & np.isfinite(b["p975_ms"])
    if band.any():
        ax.fill_between(
            s[band],
            b["p025_ms"][band],
            b["p975_ms"][band],
            color="tab:blue",
            alpha=0.2,
            lw=0,
            label="2.5–97.5 % of the frame-pair fields (PIV)",
        )
    whose = {"stiv": "STIV", "combined": "PIV and STIV combined"}.get(getattr(result.discharge, "velocities", "piv"))
    ax.plot(s, v, "-", color="tab:blue", lw=1.5, label=whose or "mean field")
    meas = ~b["filled"]
    ax.plot(s[meas], v[meas], "o", color="tab:blue", ms=5, label="measured subsection")
    if b["filled"].any():
        ax.plot(s[~meas], v[~meas], "o", mfc="white", mec="tab:orange", ms=6, label="filled from a neighbour")
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set_xlabel("station (m, left bank → right bank)")
    ax.set_ylabel("surface velocity (m/s)")
    ax.set_title("Surface velocity along the section", y=1.0)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    return "section_profile.csv", _save(fig, out / "profile.png").name


def gcp_table(project, result, to_working=None) -> list[dict]:
    """One row per measured quantity of the GCP fit: name, measured (m), fitted (m), residual (m).

    ``to_working`` maps raw-frame pixels to working pixels (undistortion); None = identity."""
    m = result.mapping
    o = project.ortho
    rows = []
    if m.method == "distances" and m.gcp_world is not None and len(o.distances_m) == 6:
        for (i, j), name, L in zip(PAIRS, NAMES, o.distances_m, strict=True):
            fit = float(np.hypot(*(m.gcp_world[j] - m.gcp_world[i])))
            rows.append({"name": name, "measured_m": float(L), "fitted_m": fit, "residual_m": fit - float(L)})
    elif m.method in ("world", "pose") and len(o.gcp_world_m):
        world = np.asarray(o.gcp_world_m, float)[:, :2]
        res = m.details.get("gcp_residual_m") if m.method == "pose" else None
        if res is None:
            px = np.asarray(o.gcp_px, float)
            got = m.image_to_world(px if to_working is None else to_working(px))
            res = np.hypot(*(got - world).T)
        for k, (w, r) in enumerate(zip(world, res, strict=True)):
            rows.append(
                {
                    "name": f"P{k + 1} ({w[0]:.3f}, {w[1]:.3f})",
                    "measured_m": None,
                    "fitted_m": None,
                    "residual_m": float(r),
                }
            )
    return rows


def write_gcp(out: Path, project, result, inputs) -> str | None:
    """``gcp.png``: the first working frame with P1..Pn, the taped distances and their residuals."""
    o = project.ortho
    if o.method == "none" or len(o.gcp_px) < 2:
        return None
    px = inputs.to_working(np.asarray(o.gcp_px, float))
    rgb = _working_rgb(inputs.first_color, inputs)
    h, w = rgb.shape[:2]
    fig = _figure(figsize=(10, 10 * h / w + 0.6))
    ax = fig.subplots()
    _show(ax, rgb, (-0.5, w - 0.5, h - 0.5, -0.5))
    rows = gcp_table(project, result, inputs.to_working)
    if o.method == "distances" and len(px) == 4:
        for (i, j), row in zip(PAIRS, rows, strict=False):  # no rows when the distances are not 6
            ax.plot(px[[i, j], 0], px[[i, j], 1], "-", color="yellow", lw=1.2, alpha=0.9)
            mid = px[[i, j]].mean(axis=0)
            ax.annotate(
                f"{row['name'].split('=')[0]} {row['measured_m']:.3f} m\nres {1000 * row['residual_m']:+.1f} mm",
                mid,
                color="black",
                fontsize=8,
                ha="center",
                va="center",
                bbox={"boxstyle": "round,pad=0.2", "fc": "yellow", "alpha": 0.8, "lw": 0},
            )
    for k, (x, y) in enumerate(px):
        ax.plot(x, y, "o", mfc="none", mec="red", ms=14, mew=2)
        label = f"P{k + 1}"
        if o.method in ("world", "pose") and k < len(rows):
            label += f"  res {1000 * rows[k]['residual_m']:.1f} mm"
        ax.annotate(
            label,
            (x, y),
            xytext=(10, -10),
            textcoords="offset points",
            color="white",
            fontsize=10,
            fontweight="bold",
            bbox={"boxstyle": "round,pad=0.2", "fc": "red", "alpha": 0.8, "lw": 0},
        )
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(f"Ground control points ({o.method}); RMS residual {1000 * result.mapping.residual_m:.1f} mm", y=1.0)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    return _save(fig, out / "gcp.png").name
