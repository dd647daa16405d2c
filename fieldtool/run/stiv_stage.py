"""STIV inside a run: search lines from the project, sampled during the PIV's frame stream, then
per-subsection STIV velocities, the STIV discharge, the PIV/STIV disagreement and the velocity source
the user chose (``[section] velocity_source`` = auto | piv | stiv | combined).

``auto`` (the default) reports the combined velocities (PIV's and STIV's, weighted per subsection by their
confidences) where the two methods agree, and PIV's where they disagree or STIV measured too little. They agree
(:func:`fieldtool.processing.stiv.agree`) when both measured 3 subsections or more and
:func:`fieldtool.processing.stiv.disagreement_reason` finds no reason: their discharges within 5 %, and the
subsections that differ by over 15 % carrying under 20 % of it. The two fail differently: PIV's windows read too
fast near the banks, where they span the steep part of the velocity profile (far_bank at 0.15 m/s: +10 to +48 %
in the outer three subsections), while STIV's narrow lines read the profile there; STIV's streak angle is misled by
waves that travel at their own speed, which PIV's tracers are not (then they disagree, and PIV is kept). Where wind
ripples lead the texture on most lines (:func:`fieldtool.processing.stiv.ripples`), PIV reads their pattern too, and
``auto`` reports STIV's velocities, read from the ripples' dispersion.

The science is in :mod:`fieldtool.processing.stiv`; this module only reads the Project and shapes the
``"stiv"`` block of ``result.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from fieldtool.errors import ParameterError
from fieldtool.processing import discharge as dq
from fieldtool.processing import stiv
from fieldtool.processing.quality import Reason
from fieldtool.project.model import Project

SOURCES = ("auto", "piv", "stiv", "combined")


@dataclass
class StivRun:
    """Lines and their space-time images for one run; ``seconds`` counts sampling and analysis."""

    acc: stiv.StiAccumulator
    n_sub: int
    normal: np.ndarray  # normal of the geometry the lines were built on
    p_img: np.ndarray  # its P1, P2 (px): tells whether the pipeline swapped them later
    seconds: float = 0.0
    sampled: bool = False

    def tap(self, frames) -> Iterator:
        """The frame stream, unchanged, with every frame sampled on the lines (timed)."""
        self.sampled = True
        for t, img in frames:
            t0 = time.perf_counter()
            self.acc.add(t, img)
            self.seconds += time.perf_counter() - t0
            yield t, img


def start(
    project: Project,
    mapping,
    geom: dq.SectionGeometry,
    shape: tuple[int, int],
    roi: tuple[int, int, int, int] | None,
    mask: np.ndarray | None,
) -> StivRun | None:
    """The STIV lines of ``project`` on ``geom`` (None when ``[stiv] enabled = false``)."""
    s = project.stiv
    if project.section.velocity_source not in SOURCES:
        raise ParameterError(
            f"section.velocity_source: {project.section.velocity_source!r} is not one of {', '.join(SOURCES)}"
        )
    if not s.enabled:
        if project.section.velocity_source not in ("piv", "auto"):
            raise ParameterError(
                f"section.velocity_source = {project.section.velocity_source!r} needs STIV: "
                'set [stiv] enabled = true or velocity_source = "piv"'
            )
        return None
    if s.method not in stiv.METHODS:
        raise ParameterError(f"stiv.method: {s.method!r} is not one of {', '.join(stiv.METHODS)}")
    valid = None
    if roi is not None or mask is not None:
        valid = np.ones(shape, bool)
        if roi is not None:
            x0, y0, x1, y1 = roi
            valid[:] = False
            valid[y0:y1, x0:x1] = True
        if mask is not None:
            valid &= ~mask
    t0 = time.perf_counter()
    lines = stiv.build_lines(
        geom.p_world,
        geom.normal,
        mapping,
        len(geom.station_edges) - 1,
        length_m=s.line_length_m,
        lines_per_sub=s.lines_per_sub,
        angles_deg=s.angles_deg,
        image_shape=shape,
        valid=valid,
    )
    run = StivRun(stiv.StiAccumulator(lines), len(geom.station_edges) - 1, geom.normal.copy(), geom.p_img.copy())
    run.seconds = time.perf_counter() - t0
    return run


def ensure_sampled(run: StivRun | None, frames: Callable[[], Iterator]) -> None:
    """Sample the lines from a stream of their own when the PIV did not stream (its field was reused)."""
    if run is not None and not run.sampled:
        for _ in run.tap(frames()):
            pass


def _piv_confidence(geom: dq.SectionGeometry, piv_res, U, V) -> np.ndarray:
    """PIV confidence per subsection (0..1): the fraction of pairs in which the nodes were valid, averaged
    over the subsection's sample points (0 where the averaged field is invalid)."""
    ok = np.isfinite(U) & np.isfinite(V)
    vf = np.where(ok, np.asarray(piv_res.valid_fraction, float), np.nan)
    a, _ = dq.sample_field(piv_res.x, piv_res.y, vf, vf, geom.sample_img)
    return np.mean(np.nan_to_num(a), axis=1)


def _flow_dir(geom: dq.SectionGeometry, x, y, U, V) -> np.ndarray:
    """PIV mean flow direction per subsection (unit world vectors; NaN where PIV has none)."""
    su, sv = dq.sample_field(x, y, U, V, geom.sample_img)
    ok = np.isfinite(su) & np.isfinite(sv)
    cnt = ok.sum(axis=1)
    mu = np.where(cnt > 0, np.where(ok, su, 0).sum(axis=1) / np.maximum(cnt, 1), np.nan)
    mv = np.where(cnt > 0, np.where(ok, sv, 0).sum(axis=1) / np.maximum(cnt, 1), np.nan)
    n = np.hypot(mu, mv)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((n > 0)[:, None], np.c_[mu / n, mv / n], np.nan)


def combine(
    v_piv: np.ndarray, w_piv: np.ndarray, v_stiv: np.ndarray, w_stiv: np.ndarray, v_fill: np.ndarray | None = None
) -> tuple[np.ndarray, list[int]]:
    """Confidence-weighted mean per subsection (m/s); where one estimate is missing (NaN or zero weight), the
    other, and the 0-based subsections where STIV's velocity was left out.

    A subsection only STIV measured has no PIV velocity to agree with (:func:`fieldtool.processing.stiv.agree`
    compares the subsections both measured): its STIV velocity is left out, and ``v_fill`` (the PIV discharge's
    velocity there, filled from the neighbours along the local Manning law) stands, where it is faster than
    ``v_fill`` by more than ``stiv.DISAGREE_REL`` of the reference speed, or upstream. A search line on the bank,
    a floating branch or the rings of rain read 8.7 m/s beside 0.2 m/s (+9 % of Q, graded good). A slower one
    is taken: STIV's narrow lines read the slow water at a bank, which the Manning law from a deeper neighbour
    over-reads (the slow far-bank scenes: +0.6 pp of Q when those were left out too). ``v_fill`` None: STIV's
    alone is taken."""
    vp = np.where(np.isfinite(v_piv) & (w_piv > 0), v_piv, np.nan)
    vs = np.where(np.isfinite(v_stiv) & (w_stiv > 0), v_stiv, np.nan)
    both = np.isfinite(vp) & np.isfinite(vs)
    left_out: list[int] = []
    if v_fill is not None:
        fill = np.asarray(v_fill, float)
        alone = np.isfinite(vs) & ~np.isfinite(vp) & np.isfinite(fill)
        top = float(np.nanmax(np.abs(vp))) if np.isfinite(vp).any() else 0.0
        ref = np.maximum(np.abs(np.nan_to_num(fill)), 0.1 * top)
        with np.errstate(invalid="ignore"):
            far = alone & ((vs - fill > stiv.DISAGREE_REL * ref) | (vs < 0))
        left_out = [int(i) for i in np.nonzero(far)[0]]
        vp = np.where(far, fill, vp)  # where STIV alone measured: ``both`` is false there already
    out = np.where(np.isfinite(vp), vp, vs)
    wsum = np.where(both, w_piv + w_stiv, 1.0)
    return np.where(both, (w_piv * np.nan_to_num(vp) + w_stiv * np.nan_to_num(vs)) / wsum, out), left_out


def finish(
    run: StivRun | None,
    project: Project,
    geom: dq.SectionGeometry,
    cs,
    level_m: float,
    dres: dq.DischargeResult,
    piv_res,
    U: np.ndarray,
    V: np.ndarray,
) -> tuple[dict | None, dq.DischargeResult]:
    """STIV per subsection on the final ``geom``; returns (the ``"stiv"`` block, the discharge result of
    the chosen velocity source: ``dres`` itself for "piv")."""
    if run is None:
        return None, dres
    t0 = time.perf_counter()
    s = project.stiv
    swapped = not np.allclose(geom.p_img, run.p_img)
    w_piv = _piv_confidence(geom, piv_res, U, V)
    flow = None
    if len(set(s.angles_deg)) > 1:
        flow = stiv.guide_directions(_flow_dir(geom, piv_res.x, piv_res.y, U, V), geom.normal, w_piv)
    only = stiv.select_lines(run.acc.lines, run.n_sub, flow, reversed_order=swapped)
    v_line, c_line = stiv.line_velocities(run.acc, s.method, only=only)
    rip = stiv.ripples(run.acc, only)  # on the lines PIV's flow directions chose
    if rip.dominated:  # wind ripples lead on most lines: each line's velocity from their dispersion
        fits = rip
        if len(set(s.angles_deg)) > 1:  # every angle, the fastest the flow's: PIV's directions follow the ripples
            fits = stiv.ripples(run.acc)
            only, flow = stiv.along_fastest(run.acc.lines, fits.velocity_ms, run.n_sub, reversed_order=swapped)
        fit = only & np.isfinite(fits.velocity_ms)
        v_line, c_line = np.where(fit, fits.velocity_ms, np.nan), np.where(fit, fits.confidence, 0.0)
    v_st, c_st, ang = stiv.subsection_velocity(
        run.acc.lines,
        v_line,
        c_line,
        run.n_sub,
        geom.normal,
        reversed_order=swapped,
        flow_dir=flow,
        min_confidence=s.min_confidence,
    )
    v_piv_raw = dq.subsection_velocity(geom, piv_res.x, piv_res.y, U, V)
    v_comb, left_out = combine(v_piv_raw, w_piv, v_st, c_st, dres.surface_velocity_ms)
    q_w = dres.alpha * dres.area_m2
    block: dict = {
        "method": s.method,
        "n_lines": len(run.acc.lines),
        "n_lines_analysed": int(only.sum()),
        "n_frames": len(run.acc.rows),
        "angles_deg": list(s.angles_deg),
        "line_length_m": s.line_length_m,
        "lines_per_sub": s.lines_per_sub,
        "velocity_ms": _clean(v_st),
        "confidence": _clean(c_st),
        "angle_deg": _clean(ang),
        "piv_velocity_ms": _clean(v_piv_raw),
        "piv_confidence": _clean(w_piv),
        "combined_velocity_ms": _clean(v_comb),
        # 1-based: measured by STIV alone, faster than the PIV's filled velocity or upstream: not combined (combine)
        "combined_left_out": [i + 1 for i in left_out],
        "disagreement": stiv.disagreement(v_piv_raw, v_st, q_w),
        "velocity_source": project.section.velocity_source,
        "ripples": rip.to_dict(),
    }
    block["disagreement_reason"] = stiv.disagreement_reason(block["disagreement"])
    alpha = project.section.alpha
    out = {}
    for name, v in (("stiv", v_st), ("combined", v_comb)):
        if np.any(np.isfinite(v)):
            out[name] = dq.compute_discharge(geom, cs, level_m, v, alpha)
    block["discharge_m3s"] = out["stiv"].discharge_m3s if "stiv" in out else None
    block["discharge_piv_m3s"] = dres.discharge_m3s
    block["discharge_combined_m3s"] = out["combined"].discharge_m3s if "combined" in out else None
    block["subsections_filled"] = int(out["stiv"].velocity_filled.sum()) if "stiv" in out else run.n_sub
    run.seconds += time.perf_counter() - t0
    block["seconds"] = round(run.seconds, 3)
    src = project.section.velocity_source
    if src == "auto" and rip.dominated and "stiv" in out:  # PIV reads the ripples' pattern, STIV their dispersion
        src = "stiv"
    elif src == "auto":  # the combined velocities where the two agree, else PIV's (module docstring)
        src = "combined" if stiv.agree(block["disagreement"]) and "combined" in out else "piv"
    block["velocity_source_used"] = src
    if src == "piv":
        return block, dres
    if src not in out:
        raise ParameterError(
            f"section.velocity_source = {src!r}: STIV found no velocity on the section "
            '(check the search lines lie on textured water, or use velocity_source = "piv")'
        )
    chosen = out[src]
    chosen.velocities = src
    if project.section.velocity_source != "auto":  # auto's choice is said in the block, not as a warning
        chosen.warnings.insert(0, f"discharge from the {src} velocities (section.velocity_source)")
    return block, chosen


def _clean(a) -> list:
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, float)]


def stiv_column(block: dict | None, n: int) -> list[str]:
    """The ``stiv_velocity_ms`` cells of subsections.csv ("" where STIV gave none)."""
    vals = (block or {}).get("velocity_ms") or [None] * n
    return ["" if v is None else f"{v:.5f}" for v in vals]


def add_reason(quality, block: dict | None) -> None:
    """Add the PIV/STIV disagreement and the wind ripples that led the lines to the quality verdict (doubtful; a
    good grade becomes doubtful)."""
    if quality is None or not block:
        return
    why = [Reason(**block["disagreement_reason"])] if block.get("disagreement_reason") else []
    rip = block.get("ripples") or {}
    if rip.get("dominated"):
        share = rip["lines_led_by_waves"] / rip["lines_fitted"]
        why.append(
            Reason(
                "ripples",
                "doubtful",
                f"wind ripples lead the texture on {rip['lines_led_by_waves']} of {rip['lines_fitted']} STIV lines: "
                "they travel on the water at their own speed, which PIV reads as the flow's; "
                + (
                    "the velocities are read from their dispersion (STIV)"
                    if block.get("velocity_source_used") == "stiv"
                    else 'section.velocity_source = "auto" or "stiv" reads the velocities from their dispersion'
                ),
                float(share),
                stiv.RIPPLES_LEAD_SHARE,
            )
        )
    quality.reasons.extend(why)
    if why and quality.grade == "good":
        quality.grade = "doubtful"
