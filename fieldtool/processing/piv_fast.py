"""The fast path to a discharge: correlate only where the discharge is measured, and stop when it has converged.

Two pieces, both pure (numpy in, numpy/dataclasses out), used by the pipeline around ``piv.analyze``:

* :func:`section_band` - the image box that feeds the discharge: the section segment(s) widened by what the
  interpolation of the field at the section, the validation neighbourhoods and the multi-pass predictor need,
  intersected with the user's ROI. ``[piv] region = "section"`` (default) correlates only this box, and in it
  only the nodes within :func:`node_reach_px` of the section (a diagonal section leaves the box's corners out);
  ``"roi"`` the user's ROI (whole frame without one) as before; ``"full"`` the whole frame.
* :func:`converge` - pairs are added in rounds, spread evenly over the clip (van der Corput order: every round
  fills the gaps the previous ones left), until the 95 % bootstrap interval
  (``processing.uncertainty.bootstrap_ci``) of the 10 %-trimmed mean per-pair discharge is narrower than
  ``rel_ci`` (half-width / |mean|, ``[piv] converge_rel_ci``, default 0.005), with at least ``min_pairs``
  pairs (``[piv] min_pairs``, default 30). Each round reads the clip again (frames are streamed, never held)
  but transforms only the frames of its own pairs; the next round's size is the one the interval's width
  predicts (the width falls as 1 / sqrt(pairs)), at least 1.5 times the pairs so far, so that few rounds
  are needed. ``[piv] all_pairs = true`` correlates every pair in one pass.
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from fieldtool.processing.uncertainty import bootstrap_ci

REGIONS = ("section", "roi", "full")


# --------------------------------------------------------------------------------------------- region


def band_margin_px(window_px: int, overlap_px: int, passes: int, search_px: int | None = None) -> int:
    """Half-width (px) of the band around a section that the discharge depends on.

    Final pass: the section's sample points are interpolated bilinearly from the nodes within one node
    spacing; those nodes are validated by a 3 x 3 median test and gaps filled from their 3 x 3 neighbours:
    three node spacings plus half a window. First pass of a multi-pass run: the predictor at those nodes is
    interpolated bicubically (two first-pass spacings), after a 3 x 3 median test and a small smoothing (one
    more spacing), from windows of ``window_px * 2**(passes-1)`` (half of it, or half the search area).
    """
    step = window_px - overlap_px
    final = 3 * step + window_px // 2 + 1
    f = 2 ** (passes - 1)
    w0, st0 = window_px * f, step * f
    s0 = max(w0, int(search_px or 0))
    first = 3 * st0 + s0 // 2 + 1 if passes > 1 else final + (s0 - w0) // 2
    return int(max(final, first))


def node_reach_px(window_px: int, overlap_px: int, passes: int) -> list[float]:
    """Per pass (first to last), the distance (px) from the section segments within which nodes are correlated
    (``piv.analyze(near=...)``); the box of :func:`section_band` holds them all.

    Final pass: a sample point reads the nodes within one spacing (bilinear), validated by a 3 x 3 median test
    and filled from 3 x 3 neighbours: three spacings, times sqrt 2 for the diagonal. An earlier pass: the next
    pass' reach plus two of its own spacings (its field is interpolated bicubically at the next pass' nodes); its
    validation and fill take the neighbours it has, and the nodes beyond are filled from them.
    """
    step = window_px - overlap_px
    reach = [3.0 * math.sqrt(2.0) * step + 1.0]
    for k in range(passes - 2, -1, -1):
        reach.insert(0, reach[0] + 2.0 * math.sqrt(2.0) * step * 2 ** (passes - 1 - k))
    return reach


def section_band(
    shape: tuple[int, int],
    segments: Iterable,
    margin_px: int,
    roi: tuple[int, int, int, int] | None = None,
    min_side_px: int = 0,
) -> tuple[int, int, int, int]:
    """Box (x0, y0, x1, y1) in pixels (x1, y1 exclusive) around the section segments, within the frame and ROI.

    Parameters
    ----------
    shape : (H, W) of the working frame, px.
    segments : iterable of (2, 2) arrays, each a section's two image points (px). Several sections give the
        box around all of them.
    margin_px : widening on every side (:func:`band_margin_px`), px.
    roi : the user's ROI box, or None.
    min_side_px : the box is grown (about its centre, inside the frame/ROI) to at least this side, so that the
        first-pass window fits.

    Returns
    -------
    (x0, y0, x1, y1) : int box; the ROI (or whole frame) when no segment is given.
    """
    h, w = int(shape[0]), int(shape[1])
    if roi is None:
        lim = (0, 0, w, h)
    else:
        rx0, ry0, rx1, ry1 = (int(c) for c in roi)
        lim = (rx0, ry0, rx1, ry1)
    pts = [np.asarray(s, float).reshape(-1, 2) for s in segments]
    pts = [p for p in pts if len(p)]
    if not pts:
        return lim
    p = np.concatenate(pts)
    x0, y0 = np.floor(p.min(axis=0)).astype(int) - margin_px
    x1, y1 = np.ceil(p.max(axis=0)).astype(int) + margin_px + 1
    box = [max(x0, lim[0]), max(y0, lim[1]), min(x1, lim[2]), min(y1, lim[3])]
    for a, b, lo, hi in ((0, 2, lim[0], lim[2]), (1, 3, lim[1], lim[3])):
        if box[b] - box[a] < min_side_px:  # grow about the centre, then shift inside the limits
            c = (box[a] + box[b]) // 2 if box[b] > box[a] else (lo + hi) // 2
            a0 = max(lo, min(c - min_side_px // 2, hi - min_side_px))
            box[a], box[b] = a0, min(hi, a0 + min_side_px)
    return int(box[0]), int(box[1]), int(box[2]), int(box[3])


# --------------------------------------------------------------------------------------------- pair order


def pair_order(n_pairs: int) -> np.ndarray:
    """All pair indices 0..n_pairs-1 in a low-discrepancy order (base-2 van der Corput): any prefix is spread
    evenly over the clip, and each longer prefix fills the gaps of the shorter one."""
    n = int(n_pairs)
    if n <= 0:
        return np.zeros(0, np.int64)
    bits = max(1, math.ceil(math.log2(n)))
    k = np.arange(2**bits, dtype=np.int64)
    rev = np.zeros_like(k)
    for b in range(bits):  # bit reversal: the van der Corput sequence times 2**bits
        rev |= ((k >> b) & 1) << (bits - 1 - b)
    idx = (rev * n) >> bits  # floor(vdc * n): every index once, since 2**bits >= n
    _, first = np.unique(idx, return_index=True)
    return idx[np.sort(first)]


# --------------------------------------------------------------------------------------------- convergence


#: share of the per-pair discharges cut at each end by the convergence test's statistic (:func:`trimmed_mean`)
TRIM = 0.1


def trimmed_mean(a: np.ndarray, axis: int = 1) -> np.ndarray:
    """Mean along ``axis`` of a 2-D array after cutting the lowest and highest :data:`TRIM` share of the values
    (at least one value is kept). A single odd pair (the first pair of a clip coded as a key frame, a glint
    burst) moves the ensemble little, since it weighs each pair's correlation by its peak ratio; the trimmed
    mean follows the ensemble, where the plain mean would call for many more pairs."""
    a = np.sort(np.asarray(a, float), axis=axis)
    n = a.shape[axis]
    k = min(int(TRIM * n), (n - 1) // 2)
    return np.take(a, np.arange(k, n - k), axis=axis).mean(axis=axis)


@dataclass
class Convergence:
    """How the pair sampling ended."""

    pairs_used: int  # pairs correlated
    pairs_total: int  # pairs in the clip (as planned from the container's frame count)
    converged: bool  # the interval got narrower than the threshold with at least min_pairs pairs
    rel_ci: float | None  # final half-width of the 95 % interval of the trimmed mean per-pair discharge / |mean|
    rounds: int  # passes over the clip
    threshold: float
    min_pairs: int


def converge(
    make_frames: Callable[..., Iterator],
    n_pairs_total: int,
    run: Callable,
    pair_q: Callable,
    rel_ci: float = 0.005,
    min_pairs: int = 30,
    seed: int = 0,
    frame_gap: int = 1,
):
    """Add pairs in rounds until the discharge's sampling uncertainty is small enough (module docstring).

    Parameters
    ----------
    make_frames : (want) -> a fresh stream of (t_s, frame) over the whole clip (read once per round); a frame at
        stream position k with ``want(k)`` false may come as (t_s, None) (not decoded: no pair of the round
        needs it). Position 0 is always wanted (it sets the frame size).
    n_pairs_total : pairs in the clip (frames - 1), from the container.
    run : run(frames, select, carry) -> piv.PivResult; ``piv.analyze`` with its other arguments bound.
    pair_q : pair_q(x, y, u_px_s, v_px_s) -> discharge (m³/s) of one pair's field.
    rel_ci : threshold on the half-width of the 95 % bootstrap interval of the trimmed mean per-pair discharge
        (:func:`trimmed_mean`), relative to that mean (0.005 = +-0.5 %).
    min_pairs : fewest pairs before the threshold is tested.
    seed : bootstrap seed (reproducible runs).
    frame_gap : frames between the two images of a pair (``PivParams.frame_gap``): pair k = frames k, k + gap.

    Returns
    -------
    (PivResult, Convergence, q_pairs) : the field over all pairs used, how it ended, and the per-pair
    discharges (m³/s, in the order of ``PivResult.u_pairs``: clip order, as ``pair_index``).
    """
    order = pair_order(n_pairs_total)
    n_total = len(order)
    done, target, rounds = 0, min(max(int(min_pairs), 2), n_total), 0
    res, rel = None, None
    q: list[float] = []
    while True:
        sel = np.sort(order[done:target])
        need = frozenset(sel.tolist()) | frozenset((sel + int(frame_gap)).tolist()) | {0}
        res = run(make_frames(need.__contains__), sel, None if res is None else res.carry)
        rounds += 1
        q.extend(pair_q(res.x, res.y, res.u_pairs[k], res.v_pairs[k]) for k in range(len(q), len(res.u_pairs)))
        done = target
        qa = np.asarray(q, float)
        lo, hi = bootstrap_ci(qa, seed=seed, stat=trimmed_mean)
        mean = float(trimmed_mean(qa[np.isfinite(qa)][None, :], axis=1)[0]) if np.isfinite(qa).any() else float("nan")
        rel = (hi - lo) / 2.0 / abs(mean) if np.isfinite(lo) and np.isfinite(mean) and mean != 0 else None
        converged = rel is not None and rel <= rel_ci and done >= min(min_pairs, n_total)
        if converged or done >= n_total:
            break
        want = done * (rel / rel_ci) ** 2 * 1.1 if rel is not None else 2 * done
        target = int(min(n_total, max(math.ceil(want), math.ceil(1.5 * done))))
    res.carry = None
    order_t = np.argsort(res.pair_index, kind="stable")  # rounds interleave: per-pair fields back in clip order
    for name in ("u_pairs", "v_pairs", "t_pairs", "dt_s", "pair_index"):
        setattr(res, name, getattr(res, name)[order_t])
    q = list(np.asarray(q, float)[order_t])
    info = Convergence(
        pairs_used=int(res.n_pairs or done),
        pairs_total=n_total,
        converged=bool(converged),
        rel_ci=None if rel is None else float(rel),
        rounds=rounds,
        threshold=float(rel_ci),
        min_pairs=int(min_pairs),
    )
    return res, info, np.asarray(q, float)


# --------------------------------------------------------------------------------------------- reader thread


class prefetch:
    """Iterate ``source`` in a background thread, ``depth`` items ahead, so that decoding (and filtering) of the
    next frames overlaps the correlation of the current pair (OpenCV and the FFTs release the GIL).

    Exceptions of the source are raised in the consumer at the item where they happened. Closing the iterator
    (or dropping it) stops the thread after at most one more item.
    """

    _END = object()

    def __init__(self, source: Iterable, depth: int = 4):
        self._q: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._stop = threading.Event()
        self._done = False
        self._thread = threading.Thread(target=self._fill, args=(iter(source),), daemon=True)
        self._thread.start()

    def _fill(self, it: Iterator) -> None:
        try:
            for item in it:
                while not self._stop.is_set():
                    try:
                        self._q.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    break
        except BaseException as e:  # noqa: BLE001 - handed to the consumer
            self._put_final((None, e))
            return
        finally:
            close = getattr(it, "close", None)
            if close is not None and self._stop.is_set():
                close()
        self._put_final((self._END, None))

    def _put_final(self, item) -> None:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def __iter__(self):
        return self

    def __next__(self):
        if self._done:
            raise StopIteration
        item, err = self._q.get()
        if err is not None:
            self._done = True
            raise err
        if item is self._END:
            self._done = True
            raise StopIteration
        return item

    def close(self) -> None:
        """Stop the reader thread (frames not consumed are dropped)."""
        self._done = True
        self._stop.set()
        self._thread.join(timeout=5.0)

    def __del__(self):
        self._stop.set()


class Prefetched:
    """A stream that a :class:`prefetch` already reads (e.g. its head replayed after a first look), with that
    reader's ``close``."""

    def __init__(self, frames: Iterable, close: Callable[[], None]):
        self._it, self._close = iter(frames), close

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._it)

    def close(self) -> None:
        self._close()


def threaded(source: Iterable, depth: int = 4) -> Iterator:
    """``source`` read by a :class:`prefetch` thread of its own, as a generator that stops that thread when it is
    closed or dropped: a stage of a pipeline of threads (decoding in one, the stationary-pattern removal in the
    next, the correlation in the caller's)."""
    reader = prefetch(source, depth)
    try:
        yield from reader
    finally:
        reader.close()
