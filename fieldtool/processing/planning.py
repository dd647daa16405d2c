"""Frame separation and search area from a first look at the clip.

Correlation is most accurate when the displacement of a pair is a few pixels and at most about a quarter of
the window (the anchors' rule of thumb: RIVeR, pyorc, PIVlab). Slow flow seen from afar moves a fraction of a
pixel per frame, where the sub-pixel error is a large share of the displacement; fast flow near the camera can
move a third of the first-pass window. A quick single-pass ensemble over the first few pairs measures the
displacement per frame of every node; the frame gap is then the largest that keeps the fast nodes within a
quarter of the first-pass window, and no larger than needed to bring the slow nodes to a few pixels. Flow too
fast for the window at one frame needs a larger first-pass search area, or a first guess: the first look's own
field (its grid is the first pass'), by which the first pass moves each B window (``piv.analyze(first_guess=)``),
so that its search area stays the window. The first guess is used when at least :data:`GUESS_MIN_VALID` of the
look's nodes have a vector and the fast nodes move at most :data:`GUESS_MAX_FRACTION` of the window (the look
correlates windows of the first pass' size, which wrap beyond half of it). Where the look cannot be trusted (fast
water at a low frame rate: a flood on a station camera filming 5 frames a second moves 60-90 px a frame), a wide
look at the frames reduced by 2, searched two windows around, plans instead and gives the first guess; else the
search area is widened. In the weak-signal plan (single pairs at the noise) the look's field is the first guess
whatever the speed, and frames averaged over a window of frames are looked at that window apart (closer ones
share noise).

The frames looked at are kept and replayed, so the stream is read once.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import cv2
import numpy as np

from fieldtool.processing import piv
from fieldtool.processing.piv_validate import fill_all

LOOK_PAIRS = 8  # pairs of the first look
#: looks at most: a look with too few vectors looks at the next pairs (a phone clip's first second: exposure or
#: focus settling)
LOOK_TRIES = 3
SLOW_TARGET_PX = 2.5  # the slow nodes (20th percentile) should move at least this far per pair
FAST_FRACTION = 0.25  # the fast nodes (95th percentile) move at most this share of the first-pass window per pair
MAX_GAP = 3
GUESS_MIN_VALID = 0.5  # share of the first look's nodes with a vector needed to use its field as the first guess
GUESS_MAX_FRACTION = 0.4  # fast nodes beyond this share of the first-pass window: the look's field is not trusted
#: the wide look (where the first cannot be trusted: fast water at a low frame rate): the frames reduced by this
#: factor, windows of the first look's footprint, searched this many windows around (displacements up to 2 w0)
WIDE_REDUCE = 2  # (a far bank's tracers are lost at 4)
WIDE_REACH = 2.0
WIDE_NODES = 400  # more windows than this at half overlap (a 4K clip's box): they do not overlap
WIDE_MIN_VALID = 0.3  # share of its nodes with a vector to plan (near the box's edges the pattern leaves it)


@dataclass
class Plan:
    """What the first look chose (px per frame are displacements between consecutive frames)."""

    frame_gap: int
    search_px: int | None
    chosen: str  # "auto" or "user"
    slow_px_per_frame: float = float("nan")  # 20th percentile of |d| over the moving nodes
    fast_px_per_frame: float = float("nan")  # 95th percentile
    pairs_looked: int = 0
    frames_skipped: int = 0  # frames before the look that planned: earlier looks found too few vectors
    reduced: int = 1  # the wide look planned: frames reduced by this factor (the first could not see that far)
    #: the wide look saw its fast nodes beyond the first look's reach but found too few vectors to plan: their
    #: displacement (px per frame) and the share of its nodes with a vector (NaN: no such look)
    unplanned_fast_px: float = float("nan")
    unplanned_valid: float = float("nan")
    #: (xc, yc, dx, dy): the look's displacement per frame (px) on its grid, when the first pass can start from it
    #: (then ``search_px`` is the wider search area that would serve instead: another engine, the user's choice)
    guess: tuple | None = None

    def as_dict(self) -> dict:
        def f(x):
            return None if not math.isfinite(x) else round(float(x), 3)

        return {
            "frame_gap": self.frame_gap,
            "search_px": self.search_px,
            "chosen": self.chosen,
            "slow_px_per_frame": f(self.slow_px_per_frame),
            "fast_px_per_frame": f(self.fast_px_per_frame),
            "pairs_looked": self.pairs_looked,
            "frames_skipped": self.frames_skipped,
            "look_reduced": self.reduced,
            "wide_look_unplanned_fast_px": f(self.unplanned_fast_px),
            "first_guess": self.guess is not None,
        }


def choose(slow_px: float, fast_px: float, first_window_px: int) -> tuple[int, int | None]:
    """Frame gap (>= 1) and first-pass search side (px, None = the window) for these displacements per frame."""
    if not (math.isfinite(slow_px) and math.isfinite(fast_px)) or fast_px <= 0:
        return 1, None
    cap = FAST_FRACTION * first_window_px
    gap_fast = max(1, int(cap // fast_px))
    gap_slow = max(1, math.ceil(SLOW_TARGET_PX / max(slow_px, 1e-6)))
    gap = int(min(gap_fast, gap_slow, MAX_GAP))
    search = None
    if fast_px > 1.2 * cap:  # too fast even at one frame: widen the first pass' search area
        search = fft_side(first_window_px + 2 * math.ceil(1.3 * fast_px))
    return gap, search


def fft_side(n: int) -> int:
    """The smallest even side >= n whose only prime factors are 2 and 3 (px): the search area's FFT is then
    1.5-2x faster than at a side with a large prime factor (124 = 4 x 31 takes 1.8x the time of 128)."""
    best = 2 ** math.ceil(math.log2(max(int(n), 2)))
    p3 = 1
    while p3 < best:
        m = 2 * p3 * 2 ** max(0, math.ceil(math.log2(max(n / (2 * p3), 1))))
        best = min(best, m)
        p3 *= 3
    return int(best)


def first_look(
    frames: Iterable[tuple[float, np.ndarray]],
    params: piv.PivParams,
    roi=None,
    mask: np.ndarray | None = None,
    gap: int = 1,
    weak: bool = False,
    hold_bytes: int | None = None,
) -> tuple[Plan, Iterator[tuple[float, np.ndarray]]]:
    """Look at the first :data:`LOOK_PAIRS` pairs and plan the frame gap and search area.

    A look whose field has fewer than 4 moving vectors (the first frames of a phone's clip, dark while the
    exposure settles or blurred while the focus hunts) looks at the next :data:`LOOK_PAIRS` pairs, up to
    :data:`LOOK_TRIES` looks and while the frames held for the replay stay within ``hold_bytes`` (None: no
    limit); ``Plan.frames_skipped`` says how many frames came before the look that planned.

    Parameters
    ----------
    frames : (t_s, image) stream, as ``piv.analyze`` takes it.
    params : the run's PIV parameters (their first-pass window is the one planned for).
    roi, mask : as ``piv.analyze``.
    gap : frames between the images of a looked pair (>= 1). Frames averaged over a window of frames
        (``processing.lowlight``) share input frames, hence noise, with their neighbours up to that window:
        pairs closer than it correlate the shared noise at zero displacement (the look read 0.05 px per frame
        for 3 px). Displacements are reported per frame whatever the gap.
    weak : single pairs are at the noise (the clip check's weak-signal plan): the look's ensemble field, where
        most of its nodes have one, is the first guess of the run's first pass whatever its frame gap, so that
        every pair's windows start from the ensemble's displacement rather than from a single pair's noise.
    hold_bytes : the most the frames held for the replay may take (bytes) before another look is tried.

    Returns
    -------
    plan : :class:`Plan` (``chosen = "auto"``).
    frames : the same stream, from its first frame (the frames looked at are replayed).
    """
    it = iter(frames)
    gap = max(int(gap), 1)
    held: list = []
    plan = Plan(frame_gap=1, search_px=None, chosen="auto")
    for _ in range(LOOK_TRIES):
        head = list(itertools.islice(it, LOOK_PAIRS + gap))
        skipped = len(held)
        held += head
        looked = _look(head, params, roi, mask, gap, weak)
        if looked is not None:
            plan = looked
            plan.frames_skipped = skipped
            break
        if skipped == 0:
            plan.pairs_looked = max(len(head) - gap, 0)  # the first look's, as said when none planned
        if len(head) < LOOK_PAIRS + gap:
            break
        if hold_bytes is not None:  # the next look holds as many frames more, of the same size
            per_frame = sum(getattr(img, "nbytes", 0) for _, img in held) / len(held)
            if per_frame * (len(held) + LOOK_PAIRS + gap) > hold_bytes:
                break
    return plan, itertools.chain(held, it)


def _look(head: list, params: piv.PivParams, roi, mask, gap: int, weak: bool) -> Plan | None:
    """The plan from one look at ``head`` (:func:`first_look`), or None where it finds fewer than 4 moving
    vectors (or too few frames, or the correlation fails).

    The look correlates windows of the first pass' side ``w0``, which see displacements up to half of it. Where
    it cannot be trusted (its fast nodes beyond :data:`GUESS_MAX_FRACTION` of ``w0``, or fewer than
    :data:`GUESS_MIN_VALID` of its nodes with a vector: fast water at a low frame rate wraps around the windows),
    the frames are looked at again, reduced by :data:`WIDE_REDUCE` (area averaging) with windows of the same
    footprint searched :data:`WIDE_REACH` windows around: a wide look that is trusted and sees its fast nodes
    beyond what the first look can see plans instead, and its field (in full-frame px) is the first pass' first
    guess."""
    w0 = params.first_window_px
    looked = _look_at(head, params, roi, mask, gap, weak, wide=False)
    if (
        looked is not None
        and looked[1] >= GUESS_MIN_VALID
        and looked[0].fast_px_per_frame * gap <= GUESS_MAX_FRACTION * w0
    ):
        return looked[0]
    wide = _look_at(head, params, roi, mask, gap, weak, wide=True)
    if wide is None or wide[0].fast_px_per_frame * gap <= GUESS_MAX_FRACTION * w0:
        return None if looked is None else looked[0]  # no wide look, or one that saw nothing the first could not
    if wide[1] >= WIDE_MIN_VALID and wide[0].guess is not None:
        return wide[0]
    # it saw the water move further, too seldom to plan from: the first look's plan (or none) stands, and the run
    # says so
    plan = looked[0] if looked is not None else Plan(1, None, "auto", pairs_looked=wide[0].pairs_looked)
    plan.unplanned_fast_px, plan.unplanned_valid = wide[0].fast_px_per_frame, wide[1]
    return plan


def _reduced(head: list, roi, mask, f: int) -> tuple[list, tuple | None, np.ndarray | None]:
    """``head``, its ROI and mask reduced by ``f`` (area averaging; a reduced pixel is masked where most of it
    is); reduced pixel i covers full-frame pixels f i .. f i + f - 1."""
    h, w = np.asarray(head[0][1]).shape[:2]
    nx, ny = w // f, h // f
    small = [
        (t, cv2.resize(np.asarray(img)[: ny * f, : nx * f], (nx, ny), interpolation=cv2.INTER_AREA)) for t, img in head
    ]
    box = None if roi is None else (roi[0] // f, roi[1] // f, -(-roi[2] // f), -(-roi[3] // f))
    m = None
    if mask is not None:
        m = cv2.resize(mask[: ny * f, : nx * f].astype(np.float32), (nx, ny), interpolation=cv2.INTER_AREA) > 0.5
    return small, box, m


def _look_at(
    head: list, params: piv.PivParams, roi, mask, gap: int, weak: bool, wide: bool
) -> tuple[Plan, float] | None:
    """One look at ``head`` (``wide``: the wide look of :func:`_look`): the plan in full-frame px and the share
    of its nodes with a vector; None as :func:`_look`."""
    w0 = params.first_window_px
    plan = Plan(frame_gap=1, search_px=None, chosen="auto", pairs_looked=max(len(head) - gap, 0))
    if len(head) < gap + 2:
        return None
    # reduction, window, overlap and search side (reduced px), reach (full px)
    f, w, overlap, search, reach = 1, w0, w0 // 2, None, w0 / 2
    if wide:
        f = WIDE_REDUCE
        w = max(w0 // f, 8)
        overlap = w // 2
        search = fft_side(w + 2 * math.ceil(WIDE_REACH * w))
        reach = f * (search - w) / 2
        head, roi, mask = _reduced(head, roi, mask, f)
        plan.reduced = f
        h, wd = head[0][1].shape[:2]
        x0, y0, x1, y1 = (0, 0, wd, h) if roi is None else roi
        if ((x1 - x0) // overlap) * ((y1 - y0) // overlap) > WIDE_NODES:
            overlap = 0
    look = replace(
        params, passes=1, window_px=w, overlap_px=overlap, search_px=search, averaging="ensemble", frame_gap=gap
    )
    try:
        res = piv.analyze(head, look, roi=roi, mask=mask)
    except Exception:  # noqa: BLE001 (a first look that fails leaves the defaults; the run reports its own error)
        return None
    # from the look's px/s (reduced px) to full-frame px per frame
    dt = f * float(np.median(res.dt_s)) / gap if res.dt_s is not None and len(res.dt_s) else 0.0
    d = (
        np.hypot(res.u, res.v)[res.valid & ~res.replaced] * dt
        if res.replaced is not None
        else np.hypot(res.u, res.v)[res.valid] * dt
    )
    d = d[np.isfinite(d)]
    if d.size < 4:
        return None
    moving = d[d >= 0.2 * np.median(d)]
    plan.slow_px_per_frame = float(np.percentile(moving, 20))
    plan.fast_px_per_frame = float(np.percentile(d, 95))
    plan.frame_gap, plan.search_px = choose(plan.slow_px_per_frame, plan.fast_px_per_frame, w0)
    ok = res.valid & np.isfinite(res.u) & np.isfinite(res.v)
    valid = float(ok.mean())
    if (
        (weak or (plan.search_px is not None and plan.frame_gap == 1))
        and valid >= (WIDE_MIN_VALID if wide else GUESS_MIN_VALID)
        and plan.fast_px_per_frame * gap <= 2 * GUESS_MAX_FRACTION * reach  # the look's pairs: within its reach
    ):
        du, dv = fill_all(np.where(ok, res.u * dt, np.nan), np.where(ok, res.v * dt, np.nan))
        xc, yc = f * res.x[0] + (f - 1) / 2, f * res.y[:, 0] + (f - 1) / 2  # a reduced pixel's centre (full px)
        plan.guess = (np.array(xc, float), np.array(yc, float), du, dv)  # px per frame; search_px the fallback
    return plan, valid
