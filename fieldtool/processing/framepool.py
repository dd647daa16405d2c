"""Whole frames recycled once nothing refers to them, for streams that write only a box of each frame.

The standardised frames (processing/surface.py, float32) and the grey frames converted only where the run
reads them (processing/video_av.py, uint8) are whole frames, 0 outside a box. A fresh frame costs its pages
each time it is written (at 4K, 8.9 ms against 1.2 ms to rewrite the box of a frame used before), so a
:class:`FramePool` hands the same frames out again once the consumers let them go.
"""

from __future__ import annotations

import mmap
import sys

import numpy as np

#: a blank frame of at least this many bytes is mapped from the kernel's zero pages (:func:`blank`)
BLANK_MAP_BYTES = 4 * 2**20
#: at most this many frames pooled, and (:func:`pool_cap`) at most ``POOL_BYTES`` of their resident memory:
#: enough for the frames in flight between a reader thread and its consumer (two queues of 4 and the pair)
POOL_FRAMES = 12
POOL_BYTES = 192 * 2**20


def blank(shape: tuple[int, int], dtype=np.float32) -> np.ndarray:
    """A frame of zeros: a large one is an anonymous memory map, whose pages cost memory and time only where
    the box is written (numpy's ``zeros`` asks for huge pages from 4 MiB on, and a 2 MiB page is zeroed and
    kept whole for the box's few pixels in each of its rows: at 4K, a float32 frame took 33 MB and 8 ms for a
    box of 3 MB)."""
    dt = np.dtype(dtype)
    n = int(np.prod(shape)) * dt.itemsize
    if n < BLANK_MAP_BYTES:
        return np.zeros(shape, dt)
    # private: a shared anonymous map is the kernel's shmem, whose page faults cost more
    buf = mmap.mmap(-1, n, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    return np.ndarray(shape, dt, buffer=buf)  # its views' base is this array


def pool_cap(shape: tuple[int, int], box: tuple[int, int, int, int], itemsize: int = 4) -> int:
    """Frames a :class:`FramePool` keeps for frames of ``shape`` (H, W) written in ``box`` (x0, y0, x1, y1
    px): what a frame holds in memory is the whole frame below :data:`BLANK_MAP_BYTES`, else the 4 KiB pages
    of the box's rows (a 4K float32 frame with a 388 px wide box: 16 MB, so 11 frames), at most the frame."""
    h, w = int(shape[0]), int(shape[1])
    x0, y0, x1, y1 = box
    whole = h * w * itemsize
    if whole < BLANK_MAP_BYTES:
        held = whole
    else:
        held = min(whole, (y1 - y0) * ((((x1 - x0) * itemsize + 4095) // 4096) + 1) * 4096)
    return max(2, min(POOL_FRAMES, POOL_BYTES // max(held, 1)))


class FramePool:
    """Whole frames (``dtype``, 0 outside the box) recycled once nothing refers to them.

    A frame handed out is read-only, so nothing can write outside its box (where a recycled frame must stay 0):
    a consumer that tried would fail loudly. A frame is free again when nothing refers to it any more: its
    CPython reference count (every view of it holds one, as its ``base``) is back to what the pool alone
    holds. Up to ``cap`` frames are pooled; beyond that a frame is a fresh one, left to the garbage collector.
    One thread takes frames from a pool; any thread may let them go.
    """

    def __init__(self, shape: tuple[int, int], cap: int = POOL_FRAMES, dtype=np.float32):
        self.shape, self.cap, self.dtype = (int(shape[0]), int(shape[1])), cap, np.dtype(dtype)
        self._frames: list[tuple[np.ndarray, int]] = []  # (frame, its reference count when only the pool holds it)

    def get(self) -> np.ndarray:
        """A writable frame, 0 outside the box (what the box holds is the caller's to overwrite)."""
        for frame, rest in self._frames:
            if sys.getrefcount(frame) == rest:
                frame.flags.writeable = True
                return frame
        frame = blank(self.shape, self.dtype)
        assert frame.base is None or not isinstance(frame.base, np.ndarray)  # it owns its memory: views count
        if len(self._frames) < self.cap:
            self._frames.append((frame, 0))
            rest = sys.getrefcount(frame)  # the references the loop above holds: the list's tuple, the local
            self._frames[-1] = (frame, rest)
        return frame

    def filled(self, box: tuple[int, int, int, int], write) -> np.ndarray:
        """A read-only frame whose box (x0, y0, x1, y1 px) ``write(view)`` has filled."""
        out = self.get()
        x0, y0, x1, y1 = box
        write(out[y0:y1, x0:x1])
        out.flags.writeable = False
        return out
