"""Self-check by internal consistency: which pre-processing variant gives the most self-consistent field.

Where the clip's estimates are ambiguous (tracer contrast neither plainly above nor plainly under the noise),
a few variants of the pre-processing are run on the first frames' pairs and scored by the field's own
consistency, never by the discharge it would give:

- frame-gap agreement (the forward-backward test's role): the velocities (px/s) from pairs g frames apart and
  from pairs 2g frames apart must agree; ``fb`` = median |u_2g - u_g| / median |u_g| over the nodes valid in both
  (0 = perfect). (Correlating b -> a instead of a -> b on the same windows only flips the sign of the same
  peak, so a literal forward-backward test on one pass is always perfect and says nothing.)
- valid fraction: the nodes' mean share of pairs with a valid vector;
- pair-to-pair spread: median over the nodes of the MAD of the per-pair speeds over the median speed.

score = valid * max(0, 1 - fb) / (1 + spread), in [0, 1]. Pure numpy + processing.piv; no file, no print.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from fieldtool.processing import piv


@dataclass
class VariantScore:
    name: str
    fb: float  # forward-backward disagreement (relative)
    valid: float  # mean valid fraction
    spread: float  # pair-to-pair spread (relative)
    score: float

    def to_dict(self) -> dict:
        def f(v):
            return round(float(v), 4) if np.isfinite(v) else None

        return {
            "name": self.name,
            "fb": f(self.fb),
            "valid": f(self.valid),
            "spread": f(self.spread),
            "score": f(self.score),
        }


def _field(frames: Sequence[np.ndarray], dt: float, params: piv.PivParams, roi, mask) -> piv.PivResult:
    return piv.analyze([(i * dt, f) for i, f in enumerate(frames)], params, roi=roi, mask=mask)


def score(
    name: str,
    frames: Sequence[np.ndarray],
    dt: float,
    params: piv.PivParams,
    roi=None,
    mask: np.ndarray | None = None,
    gap: int = 1,
) -> VariantScore:
    """Consistency of the field of ``frames`` (pre-processed, >= 4, ``dt`` s apart) under ``params``
    (averaging forced to ``mean``: per-pair fields; frame gaps ``gap`` and ``2 * gap``: with a temporal filter,
    give at least its window so that no pair shares an input frame). The passes are the project's: one pass of
    small windows cannot follow a fast flow over ``2 * gap`` frames, and both variants would score 0."""
    p = replace(params, averaging="mean", search_px=None)
    fw = _field(frames, dt, replace(p, frame_gap=gap), roi, mask)
    bw = _field(frames, dt, replace(p, frame_gap=2 * gap), roi, mask)
    both = fw.valid & bw.valid & np.isfinite(fw.u) & np.isfinite(bw.u)
    sp = np.hypot(fw.u, fw.v)
    if both.sum() < 3 or not np.isfinite(np.median(sp[both])) or np.median(sp[both]) <= 0:
        return VariantScore(name, float("nan"), float(np.nanmean(fw.valid_fraction)), float("nan"), 0.0)
    fb = float(np.median(np.hypot(bw.u - fw.u, bw.v - fw.v)[both]) / np.median(sp[both]))
    valid = float(np.nanmean(fw.valid_fraction))
    spd = np.hypot(fw.u_pairs, fw.v_pairs)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # nodes never valid: all-NaN medians
        med = np.nanmedian(spd, axis=0)
        mad = np.nanmedian(np.abs(spd - med), axis=0)
        rel = (mad / med)[both & (med > 0)]
    spread = float(np.nanmedian(rel)) if rel.size and np.isfinite(rel).any() else float("nan")
    s = valid * max(0.0, 1.0 - fb) / (1.0 + (spread if np.isfinite(spread) else 1.0))
    return VariantScore(name, fb, valid, spread, float(s))


def choose(
    variants: dict[str, Callable[[], tuple[Sequence[np.ndarray], piv.PivParams]]],
    dt: float,
    roi=None,
    mask: np.ndarray | None = None,
    gap: int = 1,
) -> tuple[str, list[VariantScore]]:
    """Score each variant (name -> () -> (pre-processed frames, params)); the name of the best and every score.
    Ties keep the first variant given (list the default first)."""
    scores = []
    for name, make in variants.items():
        try:
            fr, prm = make()
            scores.append(score(name, fr, dt, prm, roi, mask, gap))
        except Exception:  # noqa: BLE001 - a variant that cannot be scored loses
            scores.append(VariantScore(name, float("nan"), 0.0, float("nan"), 0.0))
    best = max(range(len(scores)), key=lambda i: (scores[i].score, -i))
    return scores[best].name, scores
