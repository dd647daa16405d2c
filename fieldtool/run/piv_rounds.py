"""The rounds of pairs: PIV on a growing, evenly spread sample of frame pairs until the discharge converged.

A clip of 8 s at 30 fps has 240 pairs, and the discharge is usually known to 0.5 % long before they are
all correlated. So pairs are added in rounds (``processing.piv_fast.converge`` chooses them, van der Corput
order, and judges the 95 % bootstrap interval of the per-pair discharge), and each round's frames are read
by a background thread (``processing.piv_fast.prefetch``) while the previous pair is correlated. With the
stationary-pattern removal every frame of its window must be read, so round 1 is the stream the first look
(``processing.planning``) started: :class:`SharedFirstRound` hands that stream, already reading, to the
first round, and every later round reads the clip again (a new pass), building only its own pairs' frames.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import asdict

import numpy as np

from fieldtool.errors import ParameterError
from fieldtool.processing import piv as piv_mod
from fieldtool.processing import piv_fast
from fieldtool.run.clip_pass import KeptFrames


def run_piv_fast(
    make_frames,
    n_pairs: int,
    gap: int,
    params,
    roi,
    mask,
    max_speed,
    cancel,
    on_pair,
    pair_q,
    rel_ci: float,
    min_pairs: int,
    drain_first: bool = False,
    near=None,
    first_guess=None,
):
    """PIV with pairs added until the discharge has converged (``processing.piv_fast.converge``), each round's
    frames read by a background thread (``make_frames`` may hand one already reading). ``drain_first``: the
    first round's stream is read to its end (STIV samples its lines from it). Returns (PivResult, dict of
    pairs_used, converged, ...)."""
    if not (isinstance(rel_ci, (int, float)) and np.isfinite(rel_ci) and rel_ci > 0):
        raise ParameterError(f"piv.converge_rel_ci: {rel_ci!r} must be a number above 0 (0.005 = +-0.5 %)")
    if isinstance(min_pairs, bool) or not isinstance(min_pairs, int) or min_pairs < 2:
        raise ParameterError(f"piv.min_pairs: {min_pairs!r} must be a whole number of 2 or more (30 is usual)")

    def run(frames, select, carry):
        reader = frames if isinstance(frames, (piv_fast.prefetch, piv_fast.Prefetched)) else piv_fast.prefetch(frames)
        try:
            res = piv_mod.analyze(
                reader,
                params,
                roi=roi,
                mask=mask,
                max_speed_px_s=max_speed,
                cancel=cancel,
                on_pair=on_pair,
                select=select,
                carry=carry,
                near=near,
                first_guess=first_guess,
            )
            if carry is None and drain_first:
                for _ in reader:
                    pass
            return res
        finally:
            reader.close()

    res, conv, _ = piv_fast.converge(
        make_frames, n_pairs, run, pair_q, rel_ci=rel_ci, min_pairs=min_pairs, frame_gap=gap
    )
    return res, asdict(conv)


class SharedFirstRound:
    """``make_frames(want)`` for :func:`run_piv_fast`: the first call hands the stream the first look started
    (``reader``, a ``prefetch`` still reading, its frames ``first``), setting the ``want`` its frames are
    built for; every later call replays the frames round 1's pass kept (``kept``, run/clip_pass.py) or, when
    one it wants was not kept, opens a new stream with ``stream(want=...)``."""

    def __init__(
        self,
        stream: Callable[..., Iterator],
        reader: piv_fast.prefetch | None,
        first: Iterator | None,
        round1_want: list,
        kept: KeptFrames | None = None,
    ):
        self.stream, self.reader, self.first, self.round1_want = stream, reader, first, round1_want
        self.kept = kept

    def __call__(self, want=None):
        if self.first is None:
            replay = self.kept.replay(want) if self.kept is not None and want is not None else None
            # what round 1 kept, through the rest of the stream (the standardisation), or a new pass of the clip
            return self.stream(want=want, source=replay) if replay is not None else self.stream(want=want)
        self.round1_want[0] = want
        frames, self.first = piv_fast.Prefetched(self.first, self.reader.close), None
        return frames

    def close(self) -> None:
        """Stop round 1's reader thread, even when the rounds never started (a key refused)."""
        if self.reader is not None:
            self.reader.close()
