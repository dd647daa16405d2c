"""The run's look at the clip itself before PIV (issue 23): noise, tracer contrast, glare, and the gates set from them.

Reads the first :data:`N_FRAMES` frames of the clip (raw grey, inside the PIV region), estimates them with
:mod:`fieldtool.processing.clip_stats` and derives the standardisation's soft threshold, the PIV texture gate
and the ensemble's pair count. ``facts()`` is what ``result.json`` reports under ``robust``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fieldtool.processing import clip_stats, decorrelation, lowlight, selfcheck, surface
from fieldtool.processing.surface import MIN_TEXTURE, SHRINK

#: frames read for the estimates (~0.7 s at 30 fps)
N_FRAMES = 20
#: the self-check compares pairs this many and twice as many frames apart (beyond the denoising window)
SELF_GAP = 3
#: how the reason about the frame step begins (:func:`_frame_step`)
STEP_LEAD = "the water's pattern takes"


def _user_gap(g: clip_stats.Gates, user_gap: int | None) -> clip_stats.Gates:
    if g.denoise_half and user_gap is not None and int(user_gap) < 2 * g.denoise_half + 1:
        g.denoise_half = 0
        g.reasons.append(f"piv.frame_gap = {user_gap} pairs frames closer than the denoising window: no denoising")
    return g


@dataclass
class ClipCheck:
    stats: clip_stats.ClipStats | None
    gates: clip_stats.Gates
    fps: float | None = None  # the clip's frames per second (after video.step), for the facts' seconds

    def params(self, params, standardize: bool):
        """PIV parameters with the texture gate (and, glints masked, the valid-pair share) set, only where the
        standardisation is on, as before."""
        if not standardize:
            return params
        g = self.gates
        mvf = params.min_valid_fraction if g.min_valid_fraction is None else g.min_valid_fraction
        return replace(params, min_texture=g.min_texture, min_valid_fraction=mvf)

    def before(self, frames):
        """Raw frames -> frames with the short-lived glints masked (weak clips with glare only)."""
        s = self.stats
        if not self.gates.mask_glints or s is None or s.median is None:
            return frames
        return lowlight.mask_glints(frames, s.median, s.box, s.glint_threshold, s.glare_windows)

    def std_want(self, want):
        """The standardisation builds every frame when the denoising averages them."""
        return None if self.gates.denoise_half else want

    def after(self, frames, want):
        """Standardised frames -> their temporal mean (weak clips only); ``want`` as the standardisation's."""
        return lowlight.temporal_mean(frames, self.gates.denoise_half, want) if self.gates.denoise_half else frames

    def gap(self, params):
        """Pairs of denoised frames share no input frame: frame gap at least the averaging window."""
        h = self.gates.denoise_half
        return replace(params, frame_gap=max(int(params.frame_gap), 2 * h + 1)) if h else params

    @property
    def step_said(self) -> str | None:
        """What the check said of the frame step (:func:`_frame_step`), None: nothing."""
        return next((r for r in self.gates.reasons if r.startswith(STEP_LEAD)), None)

    @property
    def weak(self) -> bool:
        """Single pairs are at the noise: the weak-signal plan (ensemble over every pair)."""
        return self.gates.min_pairs is not None

    def min_pairs(self, project_min_pairs: int) -> int:
        return max(project_min_pairs, self.gates.min_pairs or 0)

    def annotate(self, robust: dict) -> None:
        """Add the estimates and gates to ``robust`` (result.json) and the pre-processing chosen to its plan."""
        robust.update(self.facts())
        if isinstance(robust.get("plan"), dict):
            robust["plan"]["preprocessing"] = self.gates.plan

    def facts(self) -> dict:
        s = self.stats
        d = None if s is None else s.decorrelation
        return {
            "surface_change": None if d is None else d.to_dict(self.fps),
            "noise": None if s is None else {"temporal_sd_gray": s.noise, "frames": s.frames},
            "contrast": None
            if s is None
            else {
                "tracer_gray": s.contrast,
                "cnr": s.cnr,
                "texture_gray": s.texture,
                "level_gray": s.level,
                "glare_fraction": s.glare_fraction,
                "glint_threshold_gray": s.glint_threshold,  # max(GLARE_K x noise, 2 x contrast): masked above it
                "window_contrast_p10_p90": list(s.contrast_spread),
            },
            "gates": self.gates.to_dict(),
        }


def check(
    head,
    roi,
    n_clip: int,
    params=None,
    mask=None,
    standardize: bool = True,
    user_gap: int | None = None,
    no_step: str | None = None,
    fps: float | None = None,
) -> ClipCheck:
    """Estimates and gates for the clip whose first :data:`N_FRAMES` frames are ``head`` (``FrameSource.head``,
    which the run's pass replays) inside ``roi`` (x0, y0, x1, y1 px of the working frame). Where the estimates
    are ambiguous (:func:`clip_stats.ambiguous`) and the standardisation is on, the standard and the weak-signal
    gates are both run on the first frames' pairs and the more self-consistent one is kept
    (:mod:`fieldtool.processing.selfcheck`). ``user_gap``: the user's piv.frame_gap; below the denoising window
    (3 frames) the denoising is left off (pairs would share frames, hence noise). The frame step
    (``gates.step``) is set from how many frames the water's pattern takes to change (:func:`_frame_step`);
    ``no_step``: why no step may be taken (then only said), None: it may. ``fps``: the clip's frames per second."""
    got = [f for f in head if f.image is not None]
    frames = [np.asarray(f.image) for f in got]
    default = clip_stats.Gates("standard", SHRINK, MIN_TEXTURE, None, ["too few frames to estimate: default gates"])
    if len(frames) < 3:
        return ClipCheck(None, default, fps)
    stats = clip_stats.estimate(frames, roi, step=2)
    step, said = _frame_step(stats.decorrelation, n_clip, no_step, fps)
    if step > 1:  # the check's own frames as the run will read them
        got, frames = got[::step], frames[::step]
    kw: dict[str, Any] = dict(
        shrink_default=SHRINK,
        min_texture_default=MIN_TEXTURE,
        min_pairs=2,
        n_frames=-(-n_clip // step) if n_clip else len(frames),
    )
    g = _with_step(_user_gap(clip_stats.gates(stats, **kw), user_gap), step, said)
    out = ClipCheck(stats, g, fps)
    if params is None or not standardize or not clip_stats.ambiguous(stats) or len(frames) < 2 * SELF_GAP + 1:
        return out
    variants = {
        "standard": _with_step(clip_stats.gates(stats, **kw, force="standard"), step, said),
        "weak_signal": _with_step(_user_gap(clip_stats.gates(stats, **kw, force="low_light"), user_gap), step, said),
    }
    dt = float(np.median(np.diff([f.t_s for f in got]))) or 1.0 / 30.0

    def make(gv):
        def run():
            c = ClipCheck(stats, gv, fps)
            fr = surface.standardize(
                c.before(list(zip([f.t_s for f in got], frames, strict=False))),
                roi,
                half=surface.HALF_WINDOW,
                shrink=gv.shrink,
            )
            fr = c.after(fr, None)
            return [f for _, f in fr], c.params(params, True)

        return run

    best, scores = selfcheck.choose({k: make(v) for k, v in variants.items()}, dt, roi, mask, gap=SELF_GAP)
    chosen = variants[best]
    chosen.reasons.append(f"ambiguous estimates: variants scored by self-consistency, {best} kept")
    chosen.variants = [sc.to_dict() for sc in scores]
    return ClipCheck(stats, chosen, fps)


def _frame_step(d, n_clip: int, no_step: str | None, fps: float | None) -> tuple[int, str | None]:
    """The frame step the water's decorrelation asks for (processing/decorrelation.py) and what to say of it
    (None: nothing, the clip is used frame by frame as filmed). The clip keeps at least the standardisation's
    window of frames."""
    if d is None or decorrelation.step_for(d, 0, 1) <= 1:  # the water's pace asks for no step, whatever the clip
        return 1, None
    want = decorrelation.step_for(d, n_clip, 2 * surface.HALF_WINDOW + 1)  # what the clip's length allows
    secs = f" ({d.tau_frames / fps:.2f} s)" if fps else ""
    seen = (
        f"{STEP_LEAD} {d.tau_frames:.1f} frames{secs} to change at a pixel, "
        f"{d.tau_frames / decorrelation.TAU_FRAMES:.1f} x the {decorrelation.TAU_FRAMES:g} frames the method's "
        "per-frame settings are made for"
    )
    if no_step is not None:
        return 1, f"{seen}; every frame is used all the same ({no_step})"
    if want <= 1:
        return 1, f"{seen}; the clip is too short to use fewer frames (its {n_clip} frames)"
    rate = f" ({fps / want:.3g} frames per second)" if fps else ""
    return want, f"{seen}: every {_nth(want)} frame is used{rate}; video.auto_step = false uses every frame"


def _nth(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def _with_step(g: clip_stats.Gates, step: int, said: str | None) -> clip_stats.Gates:
    g.step = step
    if said:
        g.reasons.append(said)
    return g
