"""Uncertainty and quality of one run, from the Project's [uncertainty] and [quality] keys.

The thin glue between the pipeline and the pure ``processing.uncertainty`` / ``processing.quality``:
it reads the keys, rebuilds the mapping the way the run did for each Monte Carlo draw, and gathers the
evidence the quality checks read.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fieldtool.processing import ortho, pose, stiv
from fieldtool.processing import quality as ql
from fieldtool.processing import uncertainty as un
from fieldtool.processing.ortho import OrthoMapping


def thresholds(project) -> ql.Thresholds:
    """The [quality] keys as processing thresholds."""
    q = project.quality
    return ql.Thresholds(**{f.name: getattr(q, f.name) for f in dataclasses.fields(ql.Thresholds)})


def sigmas(project, level) -> un.McSigmas:
    """1-sigma of each source from the [uncertainty] keys and the level's own uncertainty."""
    u = project.uncertainty
    alpha_sigma = u.alpha_sigma
    if alpha_sigma is None:
        alpha_sigma = un.ALPHA_SIGMA_DEFAULT if project.section.alpha is None else un.ALPHA_SIGMA_GIVEN
    return un.McSigmas(
        level_m=float(level.uncertainty_m or 0.0),
        gcp_px=u.gcp_px_sigma_px,
        gcp_ref_m=u.gcp_distance_sigma_m,
        alpha=alpha_sigma,
        bed_m=u.bed_sigma_m,
        filled_rel=u.filled_rel_sigma,
        piv_rel=u.piv_rel_sigma,
    )


def _mapping_fn(project, inputs, mapping: OrthoMapping):
    """(gcp_px working, gcp_ref, level) -> H, rebuilt as the run's method did; with the GCP inputs."""
    o = project.ortho
    if o.method == "distances":
        px = inputs.to_working(np.asarray(o.gcp_px, float))
        ref = np.asarray(o.distances_m, float)

        def fn(g, r, level):
            world = ortho.gcp_world_from_distances(g, r)[0]
            return ortho.cv2.findHomography(g, world, 0)[0]

        return fn, px, ref
    if o.method == "world":
        px = inputs.to_working(np.asarray(o.gcp_px, float))
        world = np.asarray(o.gcp_world_m, float)[:, :2]

        def fn(g, r, level):
            return ortho.cv2.findHomography(g, r.reshape(-1, 2), 0)[0]

        return fn, px, world.ravel()
    if o.method == "pose":
        raw = np.asarray(o.gcp_px, float)
        world = np.asarray(o.gcp_world_m, float)
        lens = inputs.lens

        def fn(g, r, level):
            p = pose.solve_pose(g, r.reshape(-1, 3), lens.camera_matrix, lens.dist_coeffs)
            return pose.plane_homography(p, level)

        return fn, raw, world.ravel()
    if o.method == "two_points":
        px = inputs.to_working(np.asarray(o.gcp_px, float))
        if o.gcp_world_m:
            ref = np.asarray(o.gcp_world_m, float)[:, :2].ravel()

            def fn(g, r, level):
                return ortho.from_two_points(g, None, r.reshape(-1, 2)).H
        else:
            ref = np.asarray(o.distances_m[:1], float)

            def fn(g, r, level):
                return ortho.from_two_points(g, float(r[0])).H

        return fn, px, ref
    # method none: the scale comes from the outer water edges at the level
    cs = inputs.cross_section
    pts = inputs.to_working(project.section.points_px)
    length_px = float(np.hypot(*(pts[1] - pts[0])))

    def fn_scale(g, r, level):
        left, right = cs.water_edges(level)
        s = (right - left) / length_px
        return np.diag([s, -s, 1.0])

    return fn_scale, np.zeros((0, 2)), np.zeros(0)


def _suspect(dres, th: ql.Thresholds) -> tuple[np.ndarray, np.ndarray]:
    """Subsections whose measured velocity is in doubt (stalled while the neighbours move, or far below what
    their depth suggests), and the velocity each may reach (the depth envelope)."""
    v = np.where(dres.velocity_filled, np.nan, dres.surface_velocity_ms)
    out = np.zeros(len(v), bool)
    out[ql.stalled_subsections(v, th.stalled_ratio)] = True
    out[ql.deficit_subsections(v, dres.mean_depth_m, th.deficit_ratio)] = True
    return out, ql.depth_envelope(v, dres.mean_depth_m)


def _pair_blocks(res, q_pairs):
    """The per-pair fields with their deviations from the mean scaled so that the Monte Carlo's bootstrap over
    pairs gives the standard error of the mean over autocorrelated pairs, ``spread / sqrt(n_eff)`` (pairs a few
    frames apart share frames and the same eddies: resampled one by one, each would count as independent). The
    AR(1) ``n_eff`` comes from the lag-1 autocorrelation of the per-pair discharges (:func:`un.ar1_inflation`).
    Returns (u, v, the ``uncertainty.pairs`` block of result.json, None without per-pair fields)."""
    up, vp = res.u_pairs, res.v_pairs
    if up is None or vp is None or len(up) < 4 or q_pairs is None or len(q_pairs) != len(up):
        return up, vp, None
    vif, r = un.ar1_inflation(q_pairs)
    k = float(np.sqrt(vif))
    n = len(up)
    return un.inflate_deviations(up, k), un.inflate_deviations(vp, k), {"n": n, "lag1_r": r, "n_eff": n / vif}


def _stiv_faster(stiv_block: dict | None) -> list[ql.Reason]:
    """PIV and STIV disagree and STIV reads the faster discharge: a doubt that PIV under-reads (its reason, as
    the verdict adds it), which :func:`underread_bound` bounds by what STIV supports. Where STIV reads slower it
    supports no under-read, and adds no doubt here (:func:`_stiv_slower`). A drawn scene (a wide river at 1080p,
    rain, glitter and a shadow band) read -7.5 % by PIV, +0.3 % by STIV, with an interval of +-7 % that missed
    the truth."""
    return _stiv_disagrees(stiv_block, faster=True)


def _stiv_slower(stiv_block: dict | None) -> list[ql.Reason]:
    """PIV and STIV disagree and STIV reads the slower discharge: a doubt that PIV over-reads, which
    :func:`overread_bound` bounds by what STIV supports. A drawn scene (haze at 640x480, the weak-signal plan's
    temporal mean) read +27.1 % by PIV, +0.1 % by STIV, with an interval of -11 to +10 % that missed the truth."""
    return _stiv_disagrees(stiv_block, faster=False)


def _stiv_disagrees(stiv_block: dict | None, faster: bool) -> list[ql.Reason]:
    """The verdict's reason that PIV and STIV disagree, where STIV reads the faster (``faster``) or the slower
    discharge and the reported Q holds PIV's velocities; none otherwise."""
    block = stiv_block or {}
    if block.get("velocity_source_used") == "stiv":  # Q is STIV's own: PIV's error is not in it
        return []
    why, d = block.get("disagreement_reason"), (block.get("disagreement") or {}).get("discharge_relative")
    if not why or d is None:
        return []
    return [ql.Reason(**why)] if (d > 0 if faster else d < 0) else []


def underread_bound(project, doubts: list[ql.Reason], stiv_block: dict | None) -> tuple[float, dict | None]:
    """How far the velocities may be under-read (fraction) when the verdict doubts them, and what says so.

    LSPIV fails by under-reading (stationary glints and waves pull towards zero, empty seeding leaves slow
    water), so a doubt widens the interval upward. By how much is measured where the clip allows it: STIV reads
    the same section by another method, and the under-read it supports (:func:`stiv.implied_underread`, its
    disagreement with PIV plus twice its standard error) replaces the project's prior
    ``uncertainty.underread_doubtful``, never widening beyond it. Without STIV, or when the doubts make the
    run unusable (the frames themselves are in question, and STIV reads the same frames), the prior holds.
    Returns (fraction, the ``uncertainty.underread`` block of result.json, None without doubts).
    """
    if not doubts:
        return 0.0, None
    u = project.uncertainty
    unusable = any(r.severity == "unusable" for r in doubts)
    prior = u.underread_unusable if unusable else u.underread_doubtful
    implied = None if unusable else stiv.implied_underread((stiv_block or {}).get("disagreement"))
    return _read_bound(prior, implied, doubts)


def overread_bound(project, stiv_block: dict | None) -> tuple[float, dict | None]:
    """How far the velocities may be over-read (fraction) when PIV and STIV disagree and STIV reads slower, and
    what says so.

    LSPIV's usual failure is an under-read (:func:`underread_bound`), so without evidence nothing bounds an
    over-read. STIV is that evidence: where it disagrees with PIV by reading slower, the over-read it supports
    (:func:`stiv.implied_overread`, its median difference from PIV plus twice that median's standard error) widens
    the interval downward, never beyond the prior ``uncertainty.underread_doubtful``. Without a usable STIV
    difference (fewer subsections compared, or STIV upstream) nothing is added.
    Returns (fraction, the ``uncertainty.overread`` block of result.json, None without the doubt)."""
    doubts = _stiv_slower(stiv_block)
    implied = stiv.implied_overread((stiv_block or {}).get("disagreement")) if doubts else None
    if implied is None or implied["fraction"] <= 0:
        return 0.0, None
    return _read_bound(project.uncertainty.underread_doubtful, implied, doubts)


def _read_bound(prior: float, implied: dict | None, doubts: list[ql.Reason]) -> tuple[float, dict]:
    """(fraction, block) of a doubted read: STIV's bound ``implied`` (None: none), never beyond ``prior``; the
    ``uncertainty.underread`` / ``overread`` block of result.json says which one holds and the doubts."""
    frac = prior if implied is None else min(prior, implied["fraction"])
    block = {
        "max_fraction": float(frac),
        "source": "prior" if implied is None or implied["fraction"] >= prior else "stiv",
        "prior": float(prior),
        "reasons": sorted({r.code for r in doubts}),
        "stiv": implied,
    }
    return float(frac), block


def assess_run(
    project,
    inputs,
    level,
    mapping,
    geom,
    res,
    U,
    V,
    dres,
    q_pairs,
    frame_stats: dict,
    stiv_block=None,
    piv_discharge_m3s: float | None = None,
):
    """(McResult, Quality) of a finished run; never raises for a draw that fails (it is counted). ``stiv_block``
    is the run's ``"stiv"`` block (run/stiv_stage.py), None without STIV: it bounds a doubted under-read.
    ``piv_discharge_m3s``: PIV's discharge where ``dres`` is of other velocities (``section.velocity_source``):
    the Monte Carlo's draws of the PIV field are scaled to ``dres``'s."""
    sig = sigmas(project, level)
    th = thresholds(project)
    suspect, upper = _suspect(dres, th)
    fn, px, ref = _mapping_fn(project, inputs, mapping)
    u_pairs, v_pairs, blocks = _pair_blocks(res, q_pairs)
    model = un.McModel(
        cross_section=inputs.cross_section,
        level_m=level.level_m,
        section_px=geom.p_img,
        n_sub=len(geom.station_edges) - 1,
        station_offset_m=project.section.station_offset_m,
        alpha=dres.alpha,
        mapping_fn=fn,
        method=mapping.method,
        gcp_px=px,
        gcp_ref=ref,
        x=res.x,
        y=res.y,
        u=res.u,
        v=res.v,
        u_pairs=u_pairs,
        v_pairs=v_pairs,
        suspect=suspect,
        suspect_upper_ms=upper,
        trusted=geom.trusted,
    )
    dt = float(np.median(res.dt_s)) if res.dt_s is not None and len(res.dt_s) else 1.0
    p = res.params
    first = p.first_window_px  # the engine refuses passes < 1, so a result's params have 1 or more
    v_meas = np.where(dres.velocity_filled, np.nan, dres.surface_velocity_ms)
    ev = ql.Evidence(
        subsection_width_m=np.diff(geom.station_edges),
        subsection_velocity_ms=v_meas,
        subsection_depth_m=dres.mean_depth_m,
        discharge_m3s=dres.discharge_m3s,
        first_window_px=first,
        search_px=p.search_px or first,
        q_pairs_m3s=q_pairs,
        ensemble_judged=p.averaging == "ensemble" and p.min_valid_fraction == 0,
        **ql.section_evidence(
            geom.sample_img,
            geom.normal,
            res.x,
            res.y,
            res.u,
            res.v,
            U,
            V,
            dt,
            res.valid_fraction,
            res.peak,
            res.first_guess,
        ),
    )
    if frame_stats.get("pairs"):
        ev.identical_frames = frame_stats["identical"] / frame_stats["pairs"]
        ev.n_frame_pairs = frame_stats["pairs"]
    extra = []
    if mapping.details.get("residual_accepted"):
        r = mapping.residual_m
        extra.append(
            ql.Reason(
                "gcp_residual",
                "doubtful",
                f"the GCP residual ({mapping.details.get('max_distance_residual_m', r):.3f} m) exceeds "
                f"ortho.max_residual_m = {project.ortho.max_residual_m:g} m and was accepted "
                "(ortho.accept_residual)",
                float(mapping.details.get("max_distance_residual_m", r)),
                project.ortho.max_residual_m,
            )
        )
    for d in (level.details.get("doubtful") or []) if level.method == "waterline" else []:
        extra.append(ql.Reason(d["code"], "doubtful", d["message"], d.get("value"), d.get("threshold")))
    # a verdict that doubts the velocities widens the interval upward (see underread_bound)
    first_verdict = ql.assess(ev, th, extra)
    doubts = [r for r in first_verdict.reasons if r.code in ql.VELOCITY_DOUBTS] + _stiv_faster(stiv_block)
    model.underread_max, underread = underread_bound(project, doubts, stiv_block)
    model.overread_max, overread = overread_bound(project, stiv_block)
    u = project.uncertainty
    mc = un.monte_carlo_discharge(
        model,
        sig,
        dres.discharge_m3s,
        n_draws=u.n_draws,
        n_draws_source=max(u.n_draws // 4, 20),
        seed=u.seed,
        field_discharge_m3s=piv_discharge_m3s,
    )
    if blocks is not None:
        mc.notes["pairs"] = blocks
    if underread is not None:
        mc.notes["underread"] = underread
    if overread is not None:
        mc.notes["overread"] = overread
    ev.relative_u95 = mc.relative_u95
    return mc, ql.assess(ev, th, extra)
