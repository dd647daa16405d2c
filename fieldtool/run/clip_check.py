"""The run's look at the clip itself before PIV (issue 23): noise, tracer contrast, glare, and the gates set from them.

Reads the first :data:`N_FRAMES` frames of the clip (raw grey, inside the PIV region), estimates them with
:mod:`fieldtool.processing.clip_stats` and derives the standardisation's soft threshold, the PIV texture gate
and the ensemble's pair count. ``facts()`` is what ``result.json`` reports under ``robust``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fieldtool.processing import clip_stats, lowlight, selfcheck, surface
from fieldtool.processing.surface import MIN_TEXTURE, SHRINK

#: frames read for the estimates (~0.7 s at 30 fps)
N_FRAMES = 20
#: the self-check compares pairs this many and twice as many frames apart (beyond the denoising window)
SELF_GAP = 3


def _user_gap(g: clip_stats.Gates, user_gap: int | None) -> clip_stats.Gates:
    if g.denoise_half and user_gap is not None and int(user_gap) < 2 * g.denoise_half + 1:
        g.denoise_half = 0
        g.reasons.append(f"piv.frame_gap = {user_gap} pairs frames closer than the denoising window: no denoising")
    return g


@dataclass
class ClipCheck:
    stats: clip_stats.ClipStats | None
    gates: clip_stats.Gates

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
        return lowlight.mask_glints(frames, s.median, s.box, s.glint_threshold)

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
        return {
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
) -> ClipCheck:
    """Estimates and gates for the clip whose first :data:`N_FRAMES` frames are ``head`` (``FrameSource.head``,
    which the run's pass replays) inside ``roi`` (x0, y0, x1, y1 px of the working frame). Where the estimates
    are ambiguous (:func:`clip_stats.ambiguous`) and the standardisation is on, the standard and the weak-signal
    gates are both run on the first frames' pairs and the more self-consistent one is kept
    (:mod:`fieldtool.processing.selfcheck`). ``user_gap``: the user's piv.frame_gap; below the denoising window
    (3 frames) the denoising is left off (pairs would share frames, hence noise)."""
    got = [f for f in head if f.image is not None]
    frames = [np.asarray(f.image) for f in got]
    default = clip_stats.Gates("standard", SHRINK, MIN_TEXTURE, None, ["too few frames to estimate: default gates"])
    if len(frames) < 3:
        return ClipCheck(None, default)
    stats = clip_stats.estimate(frames, roi, step=2)
    kw: dict[str, Any] = dict(
        shrink_default=SHRINK, min_texture_default=MIN_TEXTURE, min_pairs=2, n_frames=n_clip or len(frames)
    )
    g = _user_gap(clip_stats.gates(stats, **kw), user_gap)
    out = ClipCheck(stats, g)
    if params is None or not standardize or not clip_stats.ambiguous(stats):
        return out
    variants = {
        "standard": clip_stats.gates(stats, **kw, force="standard"),
        "weak_signal": _user_gap(clip_stats.gates(stats, **kw, force="low_light"), user_gap),
    }
    dt = float(np.median(np.diff([f.t_s for f in got]))) or 1.0 / 30.0

    def make(gv):
        def run():
            c = ClipCheck(stats, gv)
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
    return ClipCheck(stats, chosen)
