"""Stage 5, velocimetry: the PIV field of the clip's frame pairs (px/s on the working image) and STIV's
space-time images on its search lines, sampled from the same frame stream.

:func:`setup` fixes what the PIV needs besides the frames (parameters, the box it correlates, the nodes near
the sections, the speed limit, STIV's lines); :func:`measure_velocity` streams the frames through the
stationary-pattern removal and the first look (frame gap, search area) into the PIV: in rounds of pairs
until the discharge converged (run/piv_rounds.py; one decode of the clip for every round,
run/clip_pass.py) or every pair at once (``[piv] all_pairs``), or takes the
field from the output folder's PIV cache (run/piv_cache.py) when only the geometry changed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from fieldtool.errors import ParameterError
from fieldtool.processing import piv as piv_mod
from fieldtool.processing import piv_fast, planning, surface
from fieldtool.processing.piv import PivParams
from fieldtool.project.model import Project
from fieldtool.run import camera as camera_stage
from fieldtool.run import clip_check, clip_pass, overlay_stage, piv_cache, piv_rounds, stiv_stage
from fieldtool.run import frames as frames_mod
from fieldtool.run.geometry import Sections
from fieldtool.run.inputs import Inputs
from fieldtool.run.observer import Guarded, Progress


def piv_params(project: Project):
    p = project.piv
    return PivParams(
        window_px=p.window_px,
        overlap_px=p.overlap_px,
        search_px=p.search_px,
        passes=p.passes,
        snr_min=p.snr_min,
        averaging=p.averaging,
        median_threshold=p.median_threshold,
        std_threshold=p.std_threshold,
        min_valid_fraction=p.min_valid_fraction,
        engine=p.engine,
        frame_gap=p.frame_gap or 1,
        remove_zero_peak=p.remove_zero_peak,
    )


def piv_region(project: Project, inputs: Inputs, params, roi, segments) -> tuple[int, int, int, int] | None:
    """The box PIV correlates (working-image px), by ``[piv] region``: ``section`` a band around the section
    segment(s) (list of (2, 2) working-image points) within the ROI, ``roi`` the ROI (None = whole frame),
    ``full`` the whole frame (None)."""
    region = project.piv.region
    if region not in piv_fast.REGIONS:
        raise ParameterError(f"piv.region: {region!r} is not one of {', '.join(piv_fast.REGIONS)}")
    if region == "full":
        return None
    if region == "roi":
        return roi
    margin = piv_fast.band_margin_px(params.window_px, params.overlap_px, params.passes, params.search_px)
    w0 = params.first_window_px
    side = max(w0, int(params.search_px or 0)) + 2 * (params.window_px - params.overlap_px) * 2 ** (params.passes - 1)
    return piv_fast.section_band(inputs.shape, segments, margin, roi, min_side_px=side)


def read_region(shape: tuple[int, int], box, margin: int, stiv_run) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) px: what the raw frames of a standardised stream are read in, the standardisation's
    box (the PIV's ``box`` grown by ``margin``) and STIV's lines; None: the whole frame."""
    x0, y0, x1, y1 = surface._box(shape, box, margin)
    lines = stiv_run.acc.box(shape) if stiv_run is not None else None
    if lines is not None:
        x0, y0, x1, y1 = min(x0, lines[0]), min(y0, lines[1]), max(x1, lines[2]), max(y1, lines[3])
    return None if (x0, y0, x1, y1) == (0, 0, shape[1], shape[0]) else (x0, y0, x1, y1)


#: CPU time to decode one pixel of a frame against the time to standardise one pixel of its box (processing/
#: surface.py), on the reading thread: 0.9 against 6.9 ns at 4K (``perf``, 2 cores; the STIV lines' sampling and
#: the duplicate check, about 1 ms a frame, ride with the decoding)
DECODE_PER_STD_PX = 0.9 / 6.9
#: what the reading thread does per frame besides decoding, in standardised pixels (1 ms / 6.9 ns)
READ_EXTRA_STD_PX = 145_000


def decode_bound(shape: tuple[int, int], box: tuple[int, int, int, int]) -> bool:
    """Whether decoding frames of ``shape`` (H, W px) costs more than standardising their ``box`` (x0, y0, x1, y1
    px): then the reading thread, not the standardisation, sets the pace (a 4K clip whose section's band is a
    tenth of the frame), and the decoding gets a thread of its own. 4K: 5.31 -> 5.00 s end to end; a fast 1080p
    clip (a third of its frame standardised) 3.57 -> 3.64 s and 720p 2.68 -> 2.71 s with it, so not there."""
    x0, y0, x1, y1 = box
    frame_px, box_px = int(shape[0]) * int(shape[1]), max(1, (x1 - x0) * (y1 - y0))
    return DECODE_PER_STD_PX * frame_px > box_px + READ_EXTRA_STD_PX


@dataclass
class PivSetup:
    """What the PIV needs besides the frames. ``roi`` is the box it correlates (working px, None = the whole
    frame), ``roi_user`` the user's ROI; ``near`` the section segments and node reach (px) of
    ``[piv] region = "section"``; ``max_speed`` the speed limit per node (px/s) or None."""

    params: PivParams
    standardize: bool  # stationary-pattern removal (processing.surface) on
    roi: tuple[int, int, int, int] | None
    roi_user: tuple[int, int, int, int] | None
    mask: np.ndarray | None
    near: tuple | None
    max_speed: np.ndarray | None
    stiv_run: stiv_stage.StivRun | None
    clip: clip_check.ClipCheck  # the clip's noise and contrast and the gates set from them (issue 23)
    project: Project  # the project the run goes on with: stabilised where the camera moved (run/camera.py)
    camera: camera_stage.Camera  # the camera check


def setup(
    project: Project, inputs: Inputs, mapping, sections: Sections, warnings: list[str], obs: Guarded | None = None
) -> PivSetup:
    """The PIV's parameters, box and speed limit, and STIV's lines (see :class:`PivSetup`). ``obs``: the run's
    observer (a live one sees whole frames, so the first frames are converted whole for it)."""
    roi, mask = sections.roi, sections.mask
    stiv_run = stiv_stage.start(project, mapping, sections.geom, inputs.shape, roi, mask)
    params = piv_params(project)
    # stationary-pattern removal standardises each pixel over a window of frames: a clip shorter than that
    # window (e.g. 1 s of natural texture) would lose its own texture to the window's mean
    n_clip = inputs.source.estimated_count() or 0
    standardize = project.piv.remove_stationary and (n_clip == 0 or n_clip >= 2 * surface.HALF_WINDOW + 1)
    if project.piv.remove_stationary and not standardize:
        warnings.append(
            f"piv.remove_stationary: the clip has {n_clip} frames, fewer than the "
            f"{2 * surface.HALF_WINDOW + 1} its time window needs; glints and other patterns fixed in "
            "the image are not removed"
        )
    box = piv_region(project, inputs, params, roi, sections.segments)
    # the camera check (run/camera.py) follows patches around the GCPs in the clip's first frames; where the
    # camera moved, the project comes back stabilised, and those frames are read again, whole. Then the clip's
    # noise and contrast where the PIV correlates (the section's band: the water, not the banks and sky of a
    # whole frame, whose windows would outvote it), and the texture gate set from them, from the same frames
    margin = surface.margin_for(params.search_px)
    patch_boxes = camera_stage.watch(project, inputs)
    head = inputs.source.head(
        clip_check.N_FRAMES, _head_region(project, inputs, obs, standardize, box, margin, stiv_run)
    )
    project, cam = camera_stage.check(project, inputs, head, patch_boxes, warnings)
    if cam.stabilized:
        head = inputs.source.head(
            clip_check.N_FRAMES, _head_region(project, inputs, obs, standardize, box, margin, stiv_run)
        )
    fps = getattr(getattr(inputs.source, "info", None), "fps", 0.0) or 0.0
    clip = clip_check.check(
        head,
        box if box is not None else roi,
        n_clip,
        params,
        mask,
        standardize,
        project.piv.frame_gap,
        no_step=_no_step(project),
        fps=fps / max(inputs.source.step, 1) if fps > 0 else None,
    )
    if clip.gates.step > 1:  # slow flow or a high frame rate: every n-th frame (processing/decorrelation.py)
        inputs.source.thin(clip.gates.step)
        warnings.append(f"video: {clip.step_said}")
    params = clip.params(params, standardize)  # min_texture only: the box does not depend on it
    near = None
    if project.piv.region == "section" and box is not None:  # in the band's box, only the nodes near the sections
        near = (
            [np.asarray(sg, float)[:2] for sg in sections.segments],
            piv_fast.node_reach_px(params.window_px, params.overlap_px, params.passes),
        )
    x, y = piv_mod.grid(inputs.shape, params, box)
    max_speed = None
    if project.piv.max_velocity_ms is not None:
        max_speed = project.piv.max_velocity_ms / mapping.scale_m_per_px(x, y)
    return PivSetup(params, bool(standardize), box, roi, mask, near, max_speed, stiv_run, clip, project, cam)


def _no_step(project: Project) -> str | None:
    """Why the run may not use fewer frames than the clip has (None: it may)."""
    if not project.video.auto_step:
        return "video.auto_step = false"
    if project.piv.frame_gap is not None:
        return "piv.frame_gap is set, in frames of the clip"
    if project.stabilize.enabled:  # the first frames are looked at unregistered: their change is the camera's too
        return "the frames are stabilised"
    return None


def _head_region(project: Project, inputs: Inputs, obs, standardize: bool, box, margin: int, stiv_run):
    """The box the first frames are read in (the pass' own, which replays them; None: whole)."""
    if standardize and frames_mod.in_region_ok(project, inputs, obs):
        return read_region(inputs.shape, box, margin, stiv_run)
    return None


@dataclass
class Velocimetry:
    """The velocimetry stage's output: the PIV field (``processing.piv.PivResult``) and what the frames
    told on the way. ``fast`` holds the fast path's facts (region, box, pairs used, convergence)."""

    piv: piv_mod.PivResult
    stabilization: dict
    frame_stats: dict  # {"pairs": n, "identical": n} of consecutive frames
    surface_stats: surface.SurfaceStats | None  # with the standardisation on
    plan: planning.Plan | None  # None when the field was reused
    fast: dict
    reused: bool  # the field came from the output folder's piv_cache.npz


class _Streams:
    """The frame streams the PIV reads and the pair plan (frame gap, search area) the first look sets; holds
    what every stream adds to as it is read (stabilisation report, identical frames, last time decoded)."""

    def __init__(
        self,
        project: Project,
        inputs: Inputs,
        s: PivSetup,
        cancel,
        obs: Guarded,
        progress: Progress | None,
        warnings: list[str],
    ):
        self.project, self.inputs, self.s, self.cancel, self.obs, self.progress = (
            project,
            inputs,
            s,
            cancel,
            obs,
            progress,
        )
        self.warnings = warnings
        self.params = s.params
        self.plan: planning.Plan | None = None  # set by plan_pairs
        self.stab: dict = {}
        self.frame_stats: dict = {}
        self.surface_stats = surface.SurfaceStats() if s.standardize else None
        self.decoded: list[float] = []
        self.count = clip_pass.DecodeCount()
        # px the standardisation's box reaches beyond the PIV's, for every stream of the run (the first pass'
        # search area set before the plan): the rounds standardise the same box, replayed or read again
        self.margin = surface.margin_for(s.params.search_px)

    def stream(self, want=None, tap: bool = False, keep: clip_pass.KeptFrames | None = None, source=None):
        """The frames PIV reads: working frames, duplicate count, stationary-pattern removal (which needs every
        frame of its time window: then every frame is decoded and ``want`` only chooses the standardised frames
        that are built). ``tap``: STIV samples its lines from this stream. ``keep``: what enters the
        standardisation is kept for later rounds (run/clip_pass.py); ``source``: a replay of it, read instead of
        the clip."""
        project, s = self.project, self.s
        margin = self.margin
        want_std = want
        if s.standardize:  # every frame enters the standardisation's window; only the wanted ones are built
            want = None
        elif tap and s.stiv_run is not None:  # STIV samples every frame of the stream it taps
            want = None
        if source is not None:
            frames = source
        else:
            # a frame ``want`` refuses comes with image None
            frames = frames_mod.working_frames(
                project,
                self.inputs,
                self.cancel,
                self.obs,
                self.stab if project.stabilize.enabled else None,
                self.progress,
                want=want,
                raw=s.standardize,  # the standardisation converts its box only
                count=self.count,
                region=read_region(self.inputs.shape, s.roi, margin, s.stiv_run) if s.standardize else None,
            )
            if s.standardize and decode_bound(self.inputs.shape, self.std_box()):
                frames = piv_fast.threaded(frames)  # decoding alone in a thread of its own: it sets the pace
            if tap and s.stiv_run is not None:  # STIV samples its lines from the same stream (one decode)
                frames = s.stiv_run.tap(frames)
            frames = frames_mod.count_identical(self._tracked(frames), self.frame_stats)
        if keep is not None:
            frames = keep.keeping(frames)
        if s.standardize:
            assert self.surface_stats is not None  # made in __init__ when standardising
            self.surface_stats.frames = 0  # each round of the fast path standardises the clip again: count one pass
            # decoding (and STIV's sampling) in a thread of its own; every frame has its image (want is None here)
            decoded = piv_fast.threaded(s.clip.before(frames))
            frames = surface.standardize(
                decoded,
                s.roi,
                margin=margin,
                half=surface.HALF_WINDOW,
                shrink=s.clip.gates.shrink,
                stats=self.surface_stats,
                want=s.clip.std_want(want_std),
            )
            frames = s.clip.after(frames, want_std)  # weak clips: the glints masked (before) and the temporal mean
        return frames

    def std_box(self) -> tuple[int, int, int, int]:
        """The standardisation's box (x0, y0, x1, y1 px): the PIV's box grown by :attr:`margin`."""
        return surface._box(self.inputs.shape, self.s.roi, self.margin)

    @property
    def guess(self):
        """The plan's first guess for the PIV's first pass (``plan_pairs`` has made the plan)."""
        assert self.plan is not None, "plan_pairs makes the plan before the PIV starts"
        return self.plan.guess

    def _tracked(self, it):
        for k, (t, img) in enumerate(it, start=1):
            self.decoded[:] = [t]
            self.count.in_range = max(self.count.in_range, k)
            yield t, img

    def plan_pairs(self, frames):
        """The pair plan: from a first look at the frames (``processing.planning.first_look``) unless the user
        set ``piv.frame_gap``; returns the frames, the looked ones included."""
        project, params = self.project, self.params
        if project.piv.frame_gap is None:
            clip = self.s.clip
            # denoised frames are looked at and paired beyond their averaging window; where single pairs are at
            # the noise, every pair starts from the look's ensemble field (processing/planning.py)
            plan, frames = planning.first_look(
                frames,
                params,
                self.s.roi,
                self.s.mask,
                gap=clip.gap(params).frame_gap,
                weak=clip.weak,
                hold_bytes=clip_pass.budget(self.inputs.shape),  # the frames held for another look, as kept ones
            )
            if params.search_px is not None or params.engine != "fieldtool":  # the user's search area, or an
                plan.guess = None  # engine that cannot move its windows: the wider search area instead
            if plan.guess is not None:
                plan.search_px = None  # the first pass starts from the look's field
            self.params = replace(params, frame_gap=plan.frame_gap, search_px=params.search_px or plan.search_px)
            self.params = clip.gap(self.params)
            plan.frame_gap = self.params.frame_gap
            if plan.guess is not None:  # the look's field is per frame; the first pass moves windows per pair
                xg, yg, du, dv = plan.guess
                plan.guess = (xg, yg, du * plan.frame_gap, dv * plan.frame_gap)
            if plan.frame_gap > 1 or plan.search_px or plan.guess is not None or plan.frames_skipped:
                skipped = (
                    f" (after its first {plan.frames_skipped} frames, which gave too few vectors: a phone's "
                    "exposure or focus settling?)"
                    if plan.frames_skipped
                    else ""
                )
                self.warnings.append(
                    f"piv: from a first look at {plan.pairs_looked} pairs{skipped} (slow nodes "
                    f"{plan.slow_px_per_frame:.1f}, fast nodes {plan.fast_px_per_frame:.1f} px per frame) pairs are "
                    f"{plan.frame_gap} frame(s) apart"
                    + (f" and the first pass searches {plan.search_px} px" if plan.search_px else "")
                    + (" and the first pass starts from the look's field" if plan.guess is not None else "")
                    + (
                        f" (looked at the frames reduced by {plan.reduced}: the water moves further a frame than "
                        "the first pass' windows see)"
                        if plan.reduced > 1
                        else ""
                    )
                    + "; set piv.frame_gap (and piv.search_px) to choose yourself"
                )
            if np.isfinite(plan.unplanned_fast_px):
                self.warnings.append(
                    f"piv: the water may move about {plan.unplanned_fast_px:.0f} px a frame, beyond the "
                    f"{params.first_window_px // 2} px the first look's windows see; a wider look found vectors at "
                    f"only {plan.unplanned_valid:.0%} of its nodes, too few to plan from (the pattern leaves the "
                    "region within a frame or two): film at a higher frame rate or from further away"
                )
        else:
            plan = planning.Plan(frame_gap=int(project.piv.frame_gap), search_px=params.search_px, chosen="user")
        self.plan = plan
        return frames


def measure_velocity(
    project: Project,
    inputs: Inputs,
    s: PivSetup,
    pair_q: Callable[..., float],
    cache_dir: Path | None,
    save_dir: Path | None,
    cancel,
    obs: Guarded,
    progress: Progress | None,
    warnings: list[str],
    overlay=None,
) -> Velocimetry:
    """The PIV field of the clip (and STIV's sampling on the way). ``pair_q(x, y, u, v)`` is the discharge of
    one pair's field on the main section (m³/s), which the rounds converge on; ``cache_dir``: the folder whose
    PIV cache is read (None: none); ``save_dir``: where a new one is written, the run's staging folder, so that
    it replaces the old one only with the rest of the run (run/outdir.py)."""
    st = _Streams(project, inputs, s, cancel, obs, progress, warnings)
    key = piv_cache.piv_key(project, s.max_speed, s.roi, s.near) if cache_dir is not None else ""
    cached = piv_cache.load(cache_dir, key, with_extra=True) if cache_dir is not None else None
    fast: dict[str, Any] = {
        "region": project.piv.region,
        "box_px": None if s.roi is None else list(s.roi),
        "roi_px": None if s.roi_user is None else list(s.roi_user),
    }

    def on_pair(i, t, xx, yy, u, v, valid):
        obs("pair", i, t, xx, yy, u, v, valid)

    n_exp = inputs.source.estimated_count()
    if cached is not None:
        res, stab_cached, extra = cached
        st.stab.update(stab_cached or {})
        extra = dict(extra or {})
        st.frame_stats.update(extra.pop("frame_stats", None) or {})  # identical frames are still a reason on reuse
        fast.update(extra)
    # pairs are added in rounds until the discharge converged (piv_fast.converge). The first round is one
    # streamed pass that STIV and the first look share: its reader thread decodes (and standardises) every
    # frame, but builds only the frames of the round's pairs, spread over the clip, and those kept for the
    # later rounds, which replay them (run/clip_pass.py; a new pass only for a frame the budget left out)
    elif not project.piv.all_pairs and n_exp > 2:
        res = _rounds(project, st, n_exp, pair_q, on_pair, fast)
    else:
        res = _all_pairs(project, inputs, st, n_exp, on_pair, fast, warnings)
    if cached is None and cache_dir is not None and save_dir is not None:
        piv_cache.save(save_dir, key, res, st.stab or None, {**fast, "frame_stats": st.frame_stats})
    if cached is None:  # what the PIV's streams decoded (a reused field decodes nothing for it)
        fast.update(frames_decoded=st.count.frames, frames_in_range=st.count.in_range)
    if cached is not None:  # a reused PIV field: the overlay draws from STIV's pass or its own
        overlay_stage.feed_cached(overlay, res)
    stiv_stage.ensure_sampled(s.stiv_run, lambda: frames_mod.working_frames(project, inputs, cancel, obs))
    overlay_stage.ensure_drawn(overlay, lambda: frames_mod.working_frames(project, inputs, cancel, obs, raw=True))
    return Velocimetry(res, st.stab, st.frame_stats, st.surface_stats, st.plan, fast, cached is not None)


def _rounds(project: Project, st: _Streams, n_exp: int, pair_q, on_pair, fast: dict):
    """The fast path: rounds of pairs until the discharge converged (run/piv_rounds.py). Round 1 reads the
    stream the first look started (its want is set when round 1 begins); that pass also keeps the frames later
    rounds will want (run/clip_pass.py), and STIV samples its lines from it."""
    s = st.s
    # what enters the standardisation is kept for the later rounds: every frame's raw box, or without the
    # standardisation the working frames of the likely next pairs (run/clip_pass.py)
    kept = clip_pass.KeptFrames(st.inputs.shape, st.std_box() if s.standardize else None)
    round1_want: list = [None]
    reader1 = piv_fast.prefetch(
        st.stream(want=lambda k: round1_want[0] is None or round1_want[0](k) or kept.wants(k), tap=True, keep=kept)
    )
    make_frames = piv_rounds.SharedFirstRound(st.stream, reader1, st.plan_pairs(reader1), round1_want, kept)
    params = st.params
    gap = max(1, int(params.frame_gap))
    # raw boxes as decoded are uint8 and whole working frames without filters hold whole grey levels (kept as
    # uint8, clip_pass.KeptFrames._stored); a filter's frames are float32
    bytes_px = 4 if project.filters else 1
    min_pairs = s.clip.min_pairs(project.piv.min_pairs)  # weak clips average more pairs (run/clip_check.py)
    kept.plan(n_exp, n_exp - gap, min(max(int(min_pairs), 2), n_exp - gap), gap, bytes_px)
    # the pass reaches the clip's end: for STIV, and for what is kept
    drain = s.stiv_run is not None or (kept.raw and not kept.full) or len(kept.keep or ()) > 1
    try:
        if n_exp - gap >= 2:
            res, conv = piv_rounds.run_piv_fast(
                make_frames,
                n_exp - gap,
                gap,
                params,
                s.roi,
                s.mask,
                s.max_speed,
                st.cancel,
                on_pair,
                pair_q,
                project.piv.converge_rel_ci,
                min_pairs,
                drain_first=drain,
                near=s.near,
                first_guess=st.guess,
            )
            fast.update(conv)
        else:
            frames = make_frames()
            try:
                res = piv_mod.analyze(
                    frames,
                    params,
                    roi=s.roi,
                    mask=s.mask,
                    max_speed_px_s=s.max_speed,
                    cancel=st.cancel,
                    on_pair=on_pair,
                    near=s.near,
                    first_guess=st.guess,
                )
            finally:
                getattr(frames, "close", lambda: None)()
            fast.update(pairs_used=int(res.n_pairs or 0), converged=None)
    finally:  # round 1's reader thread stops even when the rounds never started (a key refused)
        make_frames.close()
    return res


def _all_pairs(project: Project, inputs: Inputs, st: _Streams, n_exp: int, on_pair, fast: dict, warnings: list[str]):
    """Every pair in one streamed pass (``[piv] all_pairs``, or a clip of 2 frames)."""
    s = st.s
    reader = piv_fast.prefetch(st.plan_pairs(st.stream(tap=True)))
    # with the count: lets the ensemble plan which pairs get per-pair vectors
    frames: Iterable[tuple[float, np.ndarray]] = frames_mod.Sized(reader, n_exp) if n_exp else reader
    try:
        res = piv_mod.analyze(
            frames,
            st.params,
            roi=s.roi,
            mask=s.mask,
            max_speed_px_s=s.max_speed,
            progress=None,
            cancel=st.cancel,
            on_pair=on_pair,
            near=s.near,
            first_guess=st.guess,
        )
    finally:
        reader.close()
    fast.update(pairs_used=int(res.n_pairs or 0), converged=None)
    v, fps = project.video, getattr(getattr(inputs.source, "info", None), "fps", 0) or 0
    decoded = st.decoded
    if v.end_s is not None and decoded and fps > 0 and decoded[0] < v.end_s - (v.step + 1) / fps:
        warnings.append(
            f"video.end_s: the clip decoded only up to {decoded[0]:.2f} s of the {v.end_s:g} s asked "
            f"(its container claims more); the measurement covers {v.start_s:g}-{decoded[0]:.2f} s"
        )
    return res
