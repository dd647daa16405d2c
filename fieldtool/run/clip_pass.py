"""One decode per clip: the rounds of pairs read the frames of one pass over the video.

The fast path (run/piv_rounds.py) adds pairs in rounds until the discharge converged. Each round used to read
the clip again: decoding, undistorting and standardising every frame once more for a few more pairs, which on
a long clip costs more than the correlation. Here round 1's pass (the one the first look, the
standardisation window and STIV share) also keeps, in memory, what a later round would decode again, as far
as :func:`budget` holds it, and a later round replays it instead of decoding. A round that wants a frame not
kept (a clip too long for the budget) reads the clip again, as before; ``frames_decoded`` in result.json then
exceeds ``frames_in_range``.

What is kept is the stream as it enters the standardisation:

* with the standardisation (``piv.remove_stationary``, the default), every frame's raw box (the
  standardisation's box, uint8 as decoded), all or none: its window needs every frame, so a later round runs
  the standardisation again on the kept boxes. A raw box takes a quarter of a standardised one (float32), and
  most clips converge in round 1, whose pass then paid only for copies it never uses (720p: 96 MB where the
  standardised boxes of the likely next pairs took 256 MB, 0.2 s of page faults and copies);
* without it, the working frames of the next pairs in the convergence order (``piv_fast.pair_order``), whole
  (as uint8 where their values are whole grey levels, exact), as many as the budget holds.

The standardisation is deterministic, so a replayed round builds the very arrays a new pass would: the field
and the discharge are the same as with a new pass (tests/run/test_clip_pass.py).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from fieldtool.processing import framepool, piv_fast

#: memory the kept frames may take (bytes) up to 1080p (:func:`budget`): the raw boxes of 30 s at 30 fps
#: (600 x 500 px each)
KEEP_BYTES = 256 * 2**20
#: what the rest of the run holds per pixel of the frame beyond :data:`FREE_PX` (bytes: decoded frames in flight,
#: the standardised frames' rows and their pool, the decoder's own), given back by the budget: a 4K run may keep
#: ~80 MiB (the raw boxes of ~3.5 s of its section's band) and its peak stays under 1 GB
PER_PX_BYTES = 28
#: frame size (px) up to which the kept frames have the whole of KEEP_BYTES (1080p)
FREE_PX = 1920 * 1080


def budget(shape: tuple[int, int] | None) -> int:
    """The kept frames' budget (bytes) for frames of ``shape`` (H, W px): :data:`KEEP_BYTES` less
    :data:`PER_PX_BYTES` per pixel beyond :data:`FREE_PX`, at least a quarter of it."""
    px = int(shape[0]) * int(shape[1]) if shape is not None else 0
    return max(KEEP_BYTES // 4, KEEP_BYTES - PER_PX_BYTES * max(0, px - FREE_PX))


class DecodeCount:
    """Frames the decoder delivered, over every pass (``frames``), and the frames of one whole pass
    (``in_range``: the most positions one stream reached)."""

    def __init__(self) -> None:
        self.frames = 0
        self.in_range = 0


class KeptFrames:
    """What later rounds would decode again, by stream position, and every position's time.

    ``box`` given (x0, y0, x1, y1 px, the standardisation's): the raw frames entering the standardisation,
    that box of each, every position (or none, when the clip does not fit the budget). ``box`` None: the
    working frames of ``shape`` (H, W px), whole, at the positions ``plan(...)`` chooses. ``keeping(frames)``
    stores them as the pass goes by; ``replay(want)`` is a later round's stream of what was kept (the raw frames
    for the standardisation to run on again, or the wanted working frames), or None when it falls short."""

    def __init__(
        self,
        shape: tuple[int, int] | None = None,
        box: tuple[int, int, int, int] | None = None,
        budget_bytes: int | None = None,
    ):
        self.shape, self.box = shape, box
        self.budget = int(budget(shape) if budget_bytes is None else budget_bytes)
        self.keep: frozenset | None = None  # working frames: None until planned (every frame built is kept)
        self.frames: dict[int, np.ndarray] = {}
        self.times: list[float] = []
        self.complete = False  # the pass reached the clip's end
        self.held = 0  # bytes kept
        self.full = False  # raw boxes: the budget ran out, nothing is kept

    @property
    def raw(self) -> bool:
        """The raw frames' boxes are kept (the standardisation runs again on a replay)."""
        return self.box is not None

    def plan(self, n_frames: int, n_pairs_total: int, first_round: int, gap: int, bytes_per_px: int = 1) -> None:
        """Raw boxes: keep every frame's when the clip's ``n_frames`` (the container's count) fit the budget at
        ``bytes_per_px``, else none. Working frames: those of the pairs after round 1's ``first_round`` ones,
        in the convergence order, within the budget (``bytes_per_px`` 1: whole grey levels, kept as uint8; 4:
        float32)."""
        if self.raw:
            x0, y0, x1, y1 = self.box  # type: ignore[misc]
            if int(n_frames) * (x1 - x0) * (y1 - y0) * int(bytes_per_px) > self.budget:
                self._drop()
            return
        h, w = self.shape if self.shape is not None else (0, 0)
        n_fit = self.budget // max(1, int(h) * int(w) * int(bytes_per_px))
        keep: set = set()
        for p in piv_fast.pair_order(n_pairs_total)[first_round:]:
            if len(keep | {int(p), int(p) + gap}) > n_fit:
                break
            keep.update((int(p), int(p) + gap))
        keep.add(0)  # every round reads position 0 (it sets the frame size)
        self.keep = frozenset(keep)
        for k in list(self.frames):  # kept before the plan (the first look's frames): only those wanted stay
            if k not in self.keep:
                self.frames.pop(k, None)

    def wants(self, k: int) -> bool:
        """Whether the working frame at position ``k`` must be built (to be kept); a raw box needs nothing built."""
        keep = self.keep
        return not self.raw and (keep is None or k in keep)

    def keeping(self, frames: Iterator) -> Iterator:
        """The stream, unchanged, with what is kept of each position stored (copied)."""
        for k, (t, img) in enumerate(frames):
            self.times.append(float(t))
            if img is not None and (self.raw and not self.full or self.wants(k)):
                kept = self._stored(img)
                self.held += kept.nbytes
                self.frames[k] = kept
                if self.raw and self.held > self.budget:  # more frames than the container said
                    self._drop()
            yield t, img
        self.complete = True

    def _drop(self) -> None:
        self.full = True
        self.frames.clear()

    def _stored(self, img: np.ndarray) -> np.ndarray:
        """What is kept of a frame: the raw box as it is, or the whole working frame, as uint8 when its values
        are whole grey levels (no filter: exact)."""
        if self.raw:
            x0, y0, x1, y1 = self.box  # type: ignore[misc]
            return img[y0:y1, x0:x1].copy()
        if img.dtype == np.float32:
            u8 = img.astype(np.uint8)
            if np.array_equal(u8, img):
                return u8
        return img.copy()

    def replay(self, want: Callable[[int], bool]) -> Iterator | None:
        """A later round's stream, or None when the pass did not reach the end or fell short of what the round
        wants. Raw boxes: every position's raw frame (0 outside the box, read-only, recycled: the
        standardisation's input, which ``want`` does not thin). Working frames: (t_s, None) where ``want`` is
        false, else a fresh float32 frame (the round may write into it)."""
        n = len(self.times)
        if not self.complete:
            return None
        if self.raw:
            if self.full or len(self.frames) != n:
                return None
            return self._raw_stream()
        if any(want(k) and k not in self.frames for k in range(n)):
            return None
        return ((t, self.frames[k].astype(np.float32) if want(k) else None) for k, t in enumerate(self.times))

    def _raw_stream(self) -> Iterator:
        assert self.shape is not None and self.box is not None  # a raw keep has both
        first = self.frames[0]
        pool = framepool.FramePool(self.shape, framepool.pool_cap(self.shape, self.box, first.itemsize), first.dtype)
        for k, t in enumerate(self.times):
            yield t, pool.filled(self.box, lambda v, c=self.frames[k]: np.copyto(v, c))
