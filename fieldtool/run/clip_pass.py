"""One decode per clip: the rounds of pairs read the frames of one pass over the video.

The fast path (run/piv_rounds.py) adds pairs in rounds until the discharge converged. Each round used to read
the clip again: decoding, undistorting and standardising every frame once more for a few more pairs, which on
a long clip costs more than the correlation. Here round 1's pass (the one the first look, the
standardisation window and STIV share) also keeps, in memory, the standardised frames that later rounds
will likely want: the frames of the next pairs in the convergence order (``piv_fast.pair_order``, the order
the rounds take them in), as many as :func:`budget` holds. Round 1 then reads the clip to its end, and a
later round replays the kept frames instead of decoding. A round that wants a frame not kept (a clip too
long for the budget) reads the clip again, as before; ``frames_decoded`` in result.json then exceeds
``frames_in_range``.

The frames replayed are the very arrays a new pass would build (the standardisation is deterministic), so
the field and the discharge are the same as with a new pass. Only the standardised box is kept (outside it
the frames are 0, see processing/surface.py), as float32. Without the standardisation
(``piv.remove_stationary = false``) the working frames are kept whole (as uint8 without filters: whole grey
levels, exact), and STIV, when on, samples round 1's pass too (every frame is then built).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from fieldtool.processing import framepool, piv_fast

#: memory the kept frames may take (bytes) up to 1080p (:func:`budget`): ~200 standardised boxes of 600 x 500 px
KEEP_BYTES = 256 * 2**20
#: what the rest of the run holds per pixel of the frame beyond :data:`FREE_PX` (bytes: decoded frames in flight,
#: the standardised frames' rows and their pool, the decoder's own), given back by the budget: a 4K run keeps
#: ~90 MiB and its peak stays under 1 GB
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
    """The frames of round 1's pass that later rounds may want, by stream position; and every position's
    time. ``plan(...)`` chooses them once round 1's pairs are known; ``keeping(frames)`` stores them as the
    pass goes by; ``replay(want)`` is a later round's stream, or None when a wanted frame was not kept."""

    def __init__(self, stats=None, shape: tuple[int, int] | None = None, budget_bytes: int | None = None):
        # stats: processing.surface.SurfaceStats (frames are 0 outside stats.box: the box is kept), or None:
        # working frames of ``shape`` (H, W), kept whole; budget: :func:`budget` of the frame by default
        self.stats, self.shape = stats, shape
        self.budget = int(budget(shape) if budget_bytes is None else budget_bytes)
        self.keep: frozenset | None = None  # None until planned: every frame built is kept
        self.frames: dict[int, np.ndarray] = {}
        self.times: list[float] = []
        self.complete = False  # the pass reached the clip's end

    def plan(
        self, n_pairs_total: int, first_round: int, gap: int, box: tuple[int, int, int, int], bytes_per_px: int = 4
    ) -> None:
        """Keep the frames of the pairs after round 1's ``first_round`` ones, in the convergence order, within
        the budget; ``box`` is the box kept of each frame (px) and ``bytes_per_px`` what a pixel takes (4:
        float32; 1: whole working frames of whole grey levels, kept as uint8)."""
        x0, y0, x1, y1 = box
        n_fit = self.budget // max(1, (x1 - x0) * (y1 - y0) * int(bytes_per_px))
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
        """Whether the frame at position ``k`` must be built (to be kept)."""
        keep = self.keep
        return keep is None or k in keep

    def keeping(self, frames: Iterator) -> Iterator:
        """The stream, unchanged, with the kept positions' frames stored (their box, copied)."""
        for k, (t, img) in enumerate(frames):
            self.times.append(float(t))
            if img is not None and self.wants(k) and not self._static():  # static: frames passed unchanged,
                self.frames[k] = self._stored(img)  # not kept (a later round reads the clip again)
            yield t, img
        self.complete = True

    def _static(self) -> bool:
        return self.stats is not None and self.stats.static

    def _stored(self, img: np.ndarray) -> np.ndarray:
        """What is kept of a frame: the standardised box (float32), or the whole working frame, as uint8 when
        its values are whole grey levels (no filter: exact), else as it is."""
        if self.stats is not None:
            x0, y0, x1, y1 = self.stats.box
            return img[y0:y1, x0:x1].copy()
        if img.dtype == np.float32:
            u8 = img.astype(np.uint8)
            if np.array_equal(u8, img):
                return u8
        return img.copy()

    def _whole(self, crop: np.ndarray) -> np.ndarray:
        if self.stats is None:  # a fresh array (the round may write into its frames), float32 as built
            return crop.astype(np.float32) if crop.dtype == np.uint8 else crop.copy()
        out = framepool.blank(self.stats.shape)
        x0, y0, x1, y1 = self.stats.box
        out[y0:y1, x0:x1] = crop
        return out

    def replay(self, want: Callable[[int], bool]) -> Iterator | None:
        """A later round's stream from the kept frames (every position, (t_s, None) where ``want`` is false),
        or None when the pass did not reach the end or a wanted frame was not kept."""
        if not self.complete or any(want(k) and k not in self.frames for k in range(len(self.times))):
            return None
        return ((t, self._whole(self.frames[k]) if want(k) else None) for k, t in enumerate(self.times))
