"""Stage 7, quality and uncertainty: the Monte Carlo interval of the discharge and the quality verdict
(run/assess.py), STIV's disagreement with PIV as a reason, and the extra sections of interest
(project/sections.py), each measured on the run's field with its own interval and grade."""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np

from fieldtool.errors import FieldToolError
from fieldtool.processing import cross_section as xs
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho
from fieldtool.processing.quality import Quality, Reason
from fieldtool.processing.uncertainty import McResult
from fieldtool.project import sections as secs
from fieldtool.project.model import Project
from fieldtool.project.sections import SectionSpec
from fieldtool.run import camera, standard_stage, stiv_stage
from fieldtool.run.assess import assess_run
from fieldtool.run.discharge import Discharge, PairDischarge
from fieldtool.run.geometry import build_section
from fieldtool.run.inputs import Inputs
from fieldtool.run.velocimetry import Velocimetry


@dataclass
class Verdict:
    """The quality stage's output: ``uncertainty`` (processing.uncertainty.McResult) and ``quality``
    (processing.quality.Quality), None when they could not be computed; ``sections`` the entries of all
    sections when extra ones are given (the main one first), else empty."""

    uncertainty: McResult | None
    quality: Quality | None
    sections: list
    standard: dict | None = None  # ISO 748 and IVE beside the Monte Carlo, 2σ (run/standard_stage.py)


def assess(
    project: Project,
    inputs: Inputs,
    level,
    mapping: ortho.OrthoMapping,
    vel: Velocimetry,
    q: Discharge,
    pairs: PairDischarge,
    extra: list[SectionSpec],
    warnings: list[str],
) -> Verdict:
    """Interval, verdict and the extra sections (see the module's docstring); never raises for the verdict
    (the discharge is kept and the missing verdict said in the warnings)."""
    res, dres = vel.piv, q.result
    try:
        unc, qual = assess_run(
            project,
            inputs,
            level,
            mapping,
            q.geom,
            res,
            q.world_u,
            q.world_v,
            dres,
            q.q_pairs,
            vel.frame_stats,
            stiv_block=q.stiv,
            piv_discharge_m3s=q.piv_discharge_m3s,
        )
    except Exception as e:  # noqa: BLE001 - the discharge is kept; the missing verdict is said
        unc = qual = None
        warnings.append(f"uncertainty and quality not computed ({type(e).__name__}: {e}); please report this")
    stiv_stage.add_reason(qual, q.stiv)  # "PIV and STIV disagree ..." (doubtful)
    camera.add_reason(qual, q.robust.get("camera"))  # "the camera moved ..." and no registration held (doubtful)
    try:  # the hydrologists' standard uncertainty beside the Monte Carlo (issue 27)
        standard = standard_stage.compute(project, level, mapping, q.geom, res, dres)
    except Exception as e:  # noqa: BLE001 - the discharge and the Monte Carlo are kept; the gap is said
        standard = None
        warnings.append(f"ISO 748 / IVE uncertainty not computed ({type(e).__name__}: {e}); please report this")
    entries: list = []
    if extra:
        sec = project.section
        main = {
            "name": "main",
            "points_px": np.asarray(sec.points_px, float).tolist(),
            "discharge_m3s": dres.discharge_m3s,
            "discharge_ci95_m3s": (
                list(unc.ci95_m3s) if unc is not None and np.all(np.isfinite(unc.ci95_m3s)) else None
            ),
            "grade": qual.grade if qual is not None else None,
            "wetted_area_m2": dres.wetted_area_m2,
            "wetted_width_m": dres.wetted_width_m,
            "mean_velocity_ms": dres.mean_velocity_ms,
            "subsections_filled": int(dres.velocity_filled.sum()),
        }
        entries = [main] + [
            measure_section(
                project,
                inputs,
                s,
                level,
                mapping,
                res,
                q.world_u,
                q.world_v,
                vel.frame_stats,
                lambda g, cs_g: pairs.of_pairs(res, g, cs_g),
            )
            for s in extra
        ]
        for entry in entries:
            if "error" in entry:
                warnings.append(f"section {entry['name']!r}: {entry['error']}")
        _sections_reason(project, qual, secs.summarize(entries))
    return Verdict(unc, qual, entries, standard)


def _sections_reason(project: Project, qual, summ: dict | None) -> None:
    """The sections' disagreement as a reason (doubtful; a good grade becomes doubtful)."""
    if (
        qual is not None
        and summ is not None
        and summ["cv"] is not None
        and summ["cv"] > project.quality.sections_cv_doubtful
    ):
        qual.reasons.append(
            Reason(
                "sections_disagree",
                "doubtful",
                f"the {summ['n']} sections' discharges differ by a coefficient of variation of "
                f"{100 * summ['cv']:.1f} % (quality.sections_cv_doubtful = "
                f"{100 * project.quality.sections_cv_doubtful:g} %)",
                summ["cv"],
                project.quality.sections_cv_doubtful,
            )
        )
        if qual.grade == "good":
            qual.grade = "doubtful"


def measure_section(
    project, inputs, spec: SectionSpec, level, mapping, res, U, V, frame_stats: dict, pair_q_of
) -> dict:
    """Discharge, interval and grade of one extra section on the run's field; never raises for a bad section
    (its entry then holds ``error``)."""
    entry: dict = {"name": spec.name, "points_px": spec.points_px}
    try:
        cs = (
            inputs.cross_section
            if not spec.cross_section
            else xs.load_cross_section(project.resolve(spec.cross_section))
        )
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
        entry.update(
            {
                "discharge_m3s": dres.discharge_m3s,
                "discharge_ci95_m3s": ci,
                "grade": qual.grade,
                "reasons": [r.message for r in qual.reasons],
                "wetted_area_m2": dres.wetted_area_m2,
                "wetted_width_m": dres.wetted_width_m,
                "mean_velocity_ms": dres.mean_velocity_ms,
                "subsections_filled": int(dres.velocity_filled.sum()),
                "cross_section": spec.cross_section or "(the project's)",
            }
        )
    except FieldToolError as e:
        entry["error"] = str(e)
    return entry


def judge(
    project: Project,
    inputs: Inputs,
    level,
    mapping: ortho.OrthoMapping,
    vel: Velocimetry,
    q: Discharge,
    pairs: PairDischarge,
    extra: list[SectionSpec],
    warnings: list[str],
) -> Verdict:
    """:func:`assess`, or, when nothing was measured on the section (``q.unmeasured``), the verdict that grades
    it unusable with its reasons and no interval (every file is still written)."""
    if q.unmeasured is not None:
        return Verdict(None, q.unmeasured, [])
    return assess(project, inputs, level, mapping, vel, q, pairs, extra, warnings)
