"""Several sections of interest (thesis 10.3, RIVeR): the discharge of one velocity field on more sections.

The project's ``[section]`` is the main section; ``sections = [{name = "...", points_px = [[x, y], [x, y]],
cross_section = "file.csv"}, ...]`` (``station_offset_m`` optional: the first point's station, default
the left water edge) adds more, each with its own surveyed
cross-section (default: the project's) and its two water edges picked on the same frame. They share the
water level, the mapping, the PIV field, ``section.n_sub`` and ``section.alpha``. Each gets its discharge,
its 95 % interval and its quality grade as the main one does; the summary gives their mean, standard
deviation and coefficient of variation (as RIVeR's table). The headline discharge stays the main section's.

This module reads the project's keys only (project/validation.py checks them with :func:`parse`); each
section is measured by run/quality.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldtool.errors import ParameterError

SECTION_KEYS: dict[str, type | tuple[type, ...]] = {
    "name": str,
    "points_px": list,
    "cross_section": str,
    "station_offset_m": (int, float),
}


@dataclass
class SectionSpec:
    """One extra section, read from ``sections[i]``."""

    index: int
    name: str
    points_px: list
    cross_section: str
    station_offset_m: float | None  # station of the first point (m); None = the left water edge


def parse(project) -> list[SectionSpec]:
    """The extra sections of a project, checked (ParameterError naming ``sections[i].key``)."""
    out = []
    for i, item in enumerate(project.sections or []):
        k = f"sections[{i}]"
        if not isinstance(item, dict):
            raise ParameterError(f'{k}: expected a table like {{name = "upstream", points_px = [[x, y], [x, y]]}}')
        for name, v in item.items():
            if name not in SECTION_KEYS:
                raise ParameterError(f"{k}.{name}: unknown key (known: {', '.join(SECTION_KEYS)})")
            if not isinstance(v, SECTION_KEYS[name]) or isinstance(v, bool):
                raise ParameterError(f"{k}.{name}: wrong type {type(v).__name__}")
        pts = item.get("points_px", [])
        try:
            arr = np.asarray(pts, float)
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.shape != (2, 2) or not np.all(np.isfinite(arr)):
            raise ParameterError(f"{k}.points_px: give the left and the right water edge, [[x, y], [x, y]] pixels")
        off = item.get("station_offset_m")
        if off is not None and (not np.isfinite(off) or abs(off) > 1e6):
            raise ParameterError(f"{k}.station_offset_m: {off} is not a plausible station offset (m)")
        out.append(
            SectionSpec(
                i,
                str(item.get("name") or f"section {i + 2}"),
                arr.tolist(),
                str(item.get("cross_section", "")),
                None if off is None else float(off),
            )
        )
    return out


def summarize(entries: list[dict]) -> dict | None:
    """Mean, standard deviation (n-1) and coefficient of variation of the sections' discharges."""
    q = np.array([e["discharge_m3s"] for e in entries if e.get("discharge_m3s") is not None], float)
    q = q[np.isfinite(q)]
    if len(q) < 2:
        return None
    mean, std = float(q.mean()), float(q.std(ddof=1))
    return {
        "n": int(len(q)),
        "mean_m3s": mean,
        "std_m3s": std,
        "cv": std / mean if mean else None,
        "min_m3s": float(q.min()),
        "max_m3s": float(q.max()),
    }
