"""How many frames the water's pattern takes to change at a pixel, and the frame step that follows from it.

A pixel's brightness on moving water changes as the pattern (tracers, foam, texture) passes: for a pattern of
size ``l`` px moving ``d`` px per frame it stays correlated over about ``l / d`` frames. Where that time is long
(slow flow seen from afar, a clip at 60-240 fps), consecutive frames repeat each other: the standardisation's
window of frames (processing/surface.py) then holds the passing tracers themselves, and its mean erases them,
and pairs a few frames apart see sub-pixel displacements. Such a clip is sampled more finely in time than the
method needs, and every n-th frame carries its information.

:func:`fit` measures that time on the first frames of the clip (the clip check's, run/clip_check.py): the
per-pixel temporal autocorrelation at lags 1 to :data:`LAGS` of the frames less their mean, each frame first
brought to zero mean and unit spread over its pixels (an exposure settling or a fade from black changes every
pixel together, and is not the pattern changing: a 10-frame fade-in read 2-3 frame steps on fast rivers), fitted with a
Gaussian correlation ``exp(-(lag / tau)^2)`` for the share of the variance that persists plus white noise for
the rest (sensor noise, one-frame glints). The fit models what subtracting the mean of few frames does to the
autocorrelation (it pulls every lag down, the more so the longer ``tau``), so ``tau`` is not capped at the
number of frames looked at, though beyond about twice that number it is a lower bound.

:func:`step_for` turns it into a frame step: ``floor(tau / TAU_FRAMES)``, where :data:`TAU_FRAMES` is the
decorrelation time the method's per-frame defaults (the 31-frame window, pairs at most 3 frames apart) work at.
Units: frames (of the clip after ``video.step``); ``share`` is dimensionless (0-1).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

#: lags (frames) of the autocorrelation fitted
LAGS = 10
#: the decorrelation time (frames, 1/e, of the frames smoothed as the clip check smooths them: a Gaussian of
#: 1.5 px) at which the per-frame defaults work: 0.7-4.8 frames on the 37 preset and unseen scenes of
#: benchmarks/unseen_scenes.py (1.2-3.2 m/s at 25-30 fps), so none of them takes a step (that needs 7)
TAU_FRAMES = 3.5
#: below this share of persistent variance the fit is noise's, not the pattern's: no step is derived from it
#: (a glare column's one-frame glints: 0.01-0.02; a dusk clip's sensor noise leaves 0.5-0.6 after the smoothing)
MIN_SHARE = 0.3

_TAUS = np.geomspace(0.5, 100.0, 121)  # the grid of tau fitted (frames)
_SHARES = np.linspace(0.01, 1.0, 100)


@dataclass(frozen=True)
class Decorrelation:
    """The pattern's decorrelation time ``tau_frames`` (1/e, frames), the share of the variance that has it
    (0-1; the rest is white: noise, one-frame glints), the squared misfit over the lags fitted, the frames used."""

    tau_frames: float
    share: float
    misfit: float
    frames: int

    def to_dict(self, fps: float | None = None) -> dict:
        d = {
            "tau_frames": round(self.tau_frames, 2),
            "share": round(self.share, 3),
            "misfit": round(self.misfit, 4),
            "frames": self.frames,
        }
        if fps:
            d["tau_s"] = round(self.tau_frames / fps, 4)
        return d


@functools.lru_cache(maxsize=4)
def _model(n: int) -> np.ndarray:
    """Expected autocorrelation at lags 1..LAGS of ``n`` frames less their mean, for every (tau, share) of the
    grid: (len(_TAUS), len(_SHARES), LAGS). Ratio of expectations of the sums :func:`fit` takes."""
    idx = np.arange(n)
    centre = np.eye(n) - 1.0 / n  # subtracting the mean of the n frames
    lags = range(1, min(LAGS, n - 1) + 1)

    def sums(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.array([np.trace(m, k) for k in lags]),
            np.array([np.trace(m[: n - k, : n - k]) for k in lags]),
        )

    white_num, white_den = sums(centre)
    num, den = zip(
        *(sums(centre @ np.exp(-(((idx[:, None] - idx[None, :]) / t) ** 2)) @ centre) for t in _TAUS), strict=True
    )
    s = _SHARES[None, :, None]
    a, c = np.asarray(num)[:, None, :], np.asarray(den)[:, None, :]
    return (s * a + (1.0 - s) * white_num) / (s * c + (1.0 - s) * white_den)


def fit(stack: np.ndarray) -> Decorrelation | None:
    """The decorrelation of ``stack`` (n >= 4 frames, any shape after the first axis; grey levels, the frames
    whole: a change of every pixel's gain and offset together is taken out frame by frame): None where it is too
    short or holds no variance."""
    n = int(stack.shape[0])
    if n < 4:
        return None
    x = stack.reshape(n, -1).astype(np.float64)
    x -= x.mean(axis=1, keepdims=True)
    spread = x.std(axis=1, keepdims=True)
    if not (np.isfinite(spread).all() and (spread > 0).all()):
        return None
    x /= spread
    x -= x.mean(axis=0)
    gram = x @ x.T  # gram[i, j] = sum over pixels of x_i x_j
    if not np.isfinite(gram).all() or np.trace(gram) <= 0:
        return None
    lags = range(1, min(LAGS, n - 1) + 1)
    r = np.array([np.trace(gram, k) / max(np.trace(gram[: n - k, : n - k]), 1e-12) for k in lags])
    err = ((_model(n) - r) ** 2).sum(axis=2)
    i, j = np.unravel_index(int(np.argmin(err)), err.shape)
    return Decorrelation(float(_TAUS[i]), float(_SHARES[j]), float(err[i, j]), n)


def step_for(d: Decorrelation | None, n_frames: int, min_frames: int) -> int:
    """Frame step for a clip of ``n_frames`` (0 = unknown) whose pattern decorrelates as ``d``: every
    ``floor(tau / TAU_FRAMES)``-th frame, 1 where the fit is noise's (share below :data:`MIN_SHARE`), and never
    so large that fewer than ``min_frames`` frames remain."""
    if d is None or d.share < MIN_SHARE or not math.isfinite(d.tau_frames):
        return 1
    step = max(1, int(d.tau_frames // TAU_FRAMES))
    if n_frames > 0:
        step = min(step, max(1, n_frames // max(min_frames, 1)))
    return step
