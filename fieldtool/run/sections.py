"""Several sections of interest (thesis 10.3, RIVeR): the discharge of one velocity field on more sections.

The project's ``[section]`` is the main section; ``sections = [{name = "...", points_px = [[x, y], [x, y]],
cross_section = "file.csv"}, ...]`` (``station_offset_m`` optional: the first point's station, default
the left water edge) adds more, each with its own surveyed
cross-section (default: the project's) and its two water edges picked on the same frame. They share the
water level, the mapping, the PIV field, ``section.n_sub`` and ``section.alpha``. Each gets its discharge,
its 95 % interval and its quality grade as the main one does; the summary gives their mean, standard
deviation and coefficient of variation (as RIVeR's table). The headline discharge stays the main section's.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np

from fieldtool.errors import FieldToolError, ParameterError
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho

SECTION_KEYS = {"name": str, "points_px": list, "cross_section": str, "station_offset_m": (int, float)}


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
            raise ParameterError(f"{k}: expected a table like {{name = \"upstream\", points_px = [[x, y], [x, y]]}}")
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
        out.append(SectionSpec(i, str(item.get("name") or f"section {i + 2}"), arr.tolist(),
                               str(item.get("cross_section", "")), None if off is None else float(off)))
    return out


def measure(project, inputs, spec: SectionSpec, level, mapping, res, U, V, frame_stats: dict, pair_q_of) -> dict:
    """Discharge, interval and grade of one extra section on the run's field; never raises for a bad section
    (its entry then holds ``error``)."""
    from fieldtool.run.assess import assess_run
    from fieldtool.run.pipeline import build_section
    from fieldtool.processing import cross_section as xs

    entry: dict = {"name": spec.name, "points_px": spec.points_px}
    try:
        cs = inputs.cross_section if not spec.cross_section else xs.load_cross_section(project.resolve(spec.cross_section))
        cs.check_level(level.level_m)
        view = copy.deepcopy(project)
        view.section.points_px = spec.points_px
        view.section.station_offset_m = spec.station_offset_m
        vin = dataclasses.replace(inputs, cross_section=cs)
        sec = view.section
        ortho.check_in_frame(np.asarray(spec.points_px, float), inputs.shape, f"sections[{spec.index}].points_px")
        pts = np.asarray(spec.points_px, float)
        for attempt in (0, 1):
            geom = build_section(view, vin, level.level_m, mapping, points_px=pts.tolist())
            v_sub = dq.subsection_velocity(geom, res.x, res.y, U, V)
            dres = dq.compute_discharge(geom, cs, level.level_m, v_sub, sec.alpha)
            if dres.discharge_m3s >= 0 or attempt:
                break
            pts = pts[::-1]  # picked right edge first: P1 must be the left edge, as the stations assume
            entry["swapped"] = True
        q_pairs = pair_q_of(geom, cs)
        unc, qual = assess_run(view, vin, level, mapping, geom, res, U, V, dres, q_pairs, frame_stats)
        ci = list(unc.ci95_m3s) if np.all(np.isfinite(unc.ci95_m3s)) else None
        entry.update({"discharge_m3s": dres.discharge_m3s, "discharge_ci95_m3s": ci,
                      "grade": qual.grade, "reasons": [r.message for r in qual.reasons],
                      "wetted_area_m2": dres.wetted_area_m2, "wetted_width_m": dres.wetted_width_m,
                      "mean_velocity_ms": dres.mean_velocity_ms, "subsections_filled": int(dres.velocity_filled.sum()),
                      "cross_section": spec.cross_section or "(the project's)"})
    except FieldToolError as e:
        entry["error"] = str(e)
    return entry


def summarize(entries: list[dict]) -> dict | None:
    """Mean, standard deviation (n-1) and coefficient of variation of the sections' discharges."""
    q = np.array([e["discharge_m3s"] for e in entries if e.get("discharge_m3s") is not None], float)
    q = q[np.isfinite(q)]
    if len(q) < 2:
        return None
    mean, std = float(q.mean()), float(q.std(ddof=1))
    return {"n": int(len(q)), "mean_m3s": mean, "std_m3s": std, "cv": std / mean if mean else None,
            "min_m3s": float(q.min()), "max_m3s": float(q.max())}
