"""The station's time series: discharge (with its 95 % interval) and water level over time, the quality grade
as the marker colour. Times are ISO 8601 UTC text as the history stores them; Q in m³/s, levels in m."""

from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

GRADE_COLOURS = {"good": "#1a7f37", "doubtful": "#bf8700", "unusable": "#cf222e"}
NO_GRADE = "#57606a"


def parse_utc(text: str) -> datetime:
    """``2024-05-01T10:22:33Z`` (or with an offset) -> an aware datetime."""
    return datetime.fromisoformat(text.replace("Z", "+00:00"))


def plot_timeseries(path: Path | str, rows: list[dict], *, site: str = "") -> Path:
    """PNG (or PDF/SVG by suffix) of ``rows``: dicts with ``time`` (ISO UTC), ``discharge_m3s``,
    ``ci95_lo_m3s``/``ci95_hi_m3s`` (or None), ``water_level_m`` and ``grade``. Returns the path."""
    path = Path(path)
    fig = Figure(figsize=(9, 5.5), dpi=110)
    ax_q, ax_h = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    rows = [r for r in rows if r.get("time")]
    if rows:
        t = [parse_utc(r["time"]) for r in rows]
        q = np.array([np.nan if r.get("discharge_m3s") is None else r["discharge_m3s"] for r in rows], float)
        lo = np.array([np.nan if r.get("ci95_lo_m3s") is None else r["ci95_lo_m3s"] for r in rows], float)
        hi = np.array([np.nan if r.get("ci95_hi_m3s") is None else r["ci95_hi_m3s"] for r in rows], float)
        h = np.array([np.nan if r.get("water_level_m") is None else r["water_level_m"] for r in rows], float)
        colours = [GRADE_COLOURS.get(r.get("grade") or "", NO_GRADE) for r in rows]
        ax_q.plot(t, q, color="0.7", lw=1, zorder=1)
        ok = np.isfinite(lo) & np.isfinite(hi)
        if ok.any():
            ti = [x for x, k in zip(t, ok, strict=False) if k]
            ax_q.vlines(
                ti,
                lo[ok],
                hi[ok],
                color=[c for c, k in zip(colours, ok, strict=False) if k],
                lw=1.5,
                alpha=0.6,
                zorder=2,
            )
        ax_q.scatter(t, q, c=colours, s=28, zorder=3, edgecolors="white", linewidths=0.5)
        ax_h.plot(t, h, color="#0969da", lw=1, marker="o", ms=3)
        if (max(t) - min(t)).total_seconds() < 60:  # one time only: an hour around it, not years
            ax_h.set_xlim(min(t) - timedelta(minutes=30), max(t) + timedelta(minutes=30))
        for name, c in [*GRADE_COLOURS.items(), ("no grade", NO_GRADE)]:
            ax_q.scatter([], [], c=c, s=28, label=name)
        ax_q.legend(loc="best", fontsize=8, title="grade (bars: 95 % interval)", title_fontsize=8)
    else:
        ax_q.text(0.5, 0.5, "no measurement yet", ha="center", va="center", transform=ax_q.transAxes, color="0.4")
    ax_q.set_ylabel("discharge Q (m³/s)")
    ax_h.set_ylabel("water level (m)")
    ax_h.set_xlabel("time of the clip (UTC)")
    ax_q.set_title(f"station {site}: {len(rows)} measurement(s)" if site else f"{len(rows)} measurement(s)")
    for ax in (ax_q, ax_h):
        ax.grid(alpha=0.3)
    fig.autofmt_xdate()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fig.savefig(tmp, format=path.suffix.lstrip(".") or "png")
    tmp.replace(path)
    return path
