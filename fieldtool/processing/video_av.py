"""Grey frames of a video decoded by PyAV (FFmpeg), straight from the decoder's luma plane.

OpenCV's reader converts every decoded frame to BGR and the run converts it back to grey: at 4K that is more
work than the decoding itself. Here the grey frame is the luma plane (Y) of the decoded YUV frame, mapped
through a table of one grey level per luma level, built once per clip: FFmpeg's YUV -> BGR24 of each Y at the
clip's typical chroma (the median U and V of the first frame), then ``cv2.COLOR_BGR2GRAY``.

* 8-bit frames (256 levels): the grey level OpenCV gives. For grey scenes the frames are the very frames OpenCV
  decodes; elsewhere a pixel differs by the colour of its chroma from the typical one (a grey level or two in
  saturated colours).
* 10- and 12-bit frames (:data:`DEEP_FORMATS`: an iPhone's HDR HEVC, ProRes): 1024 or 4096 levels, FFmpeg's own
  grey. OpenCV's BGR of such a frame takes 45 ms a 720p frame (2 s for the first) and saturates the highlights
  of HLG (luma 700 of 1023 read 238); its colour frame is FFmpeg's BGR too (:func:`deep_frame`).

:func:`open_clip` says whether a clip is read this way (planar YUV of 8, 10 or 12 bits, no rotation in the
metadata, the same size as OpenCV's first frame, timestamps on every frame); the caller falls back to OpenCV
otherwise. Times are the frames' presentation times from the stream's start (s), as OpenCV's
``CAP_PROP_POS_MSEC``.
"""

from __future__ import annotations

from collections.abc import Iterator

import av
import cv2
import numpy as np

from fieldtool.processing.framepool import FramePool, pool_cap

#: pixel formats of three 8-bit planes, the first the luma the table maps
LUMA_FORMATS = frozenset({"yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "yuv411p", "yuv440p"})
#: pixel formats of three planes of 10 or 12 bits in little-endian 16-bit words (HDR HEVC, ProRes): their bits
DEEP_FORMATS = {f"yuv4{s}p{b}le": b for s in ("20", "22", "44") for b in (10, 12)}


def readable(fmt: str) -> bool:
    """Whether frames of pixel format ``fmt`` are read here."""
    return fmt in LUMA_FORMATS or fmt in DEEP_FORMATS


def _dtype(fmt: str) -> type:
    return np.uint16 if fmt in DEEP_FORMATS else np.uint8


def _plane(p, dtype: type = np.uint8) -> np.ndarray:
    """A plane of a decoded frame as (H, line size in samples) of ``dtype``, a view of the decoder's buffer."""
    return np.frombuffer(p, dtype).reshape(p.height, p.line_size // np.dtype(dtype).itemsize)


def _luma(frame) -> np.ndarray:
    """The Y plane of ``frame`` (H x W, uint8 or uint16, a view of the decoder's buffer)."""
    p = frame.planes[0]
    return _plane(p, _dtype(frame.format.name))[:, : p.width]


def _lookup(luma: np.ndarray, table: np.ndarray, dst: np.ndarray | None = None) -> np.ndarray:
    """``table[luma]`` as uint8 (into ``dst``): OpenCV's lookup for 8-bit luma, NumPy's for deeper."""
    if luma.dtype == np.uint8:
        return cv2.LUT(luma, table, dst=dst)
    return np.take(table, luma, out=dst, mode="clip")


def grey_table(frame) -> np.ndarray:
    """A grey level (uint8) per luma level (256, or 2^bits): FFmpeg's BGR24 of each luma value at the frame's
    median chroma, then OpenCV's grey."""
    fmt = frame.format.name
    dt = _dtype(fmt)
    levels = 1 << DEEP_FORMATS.get(fmt, 8)
    probe = av.VideoFrame(levels, 16, fmt)
    probe.color_range = frame.color_range
    for i, (src, dst) in enumerate(zip(frame.planes, probe.planes, strict=True)):
        a = _plane(dst, dt)
        if i == 0:
            a[:] = 0
            a[:, :levels] = np.arange(levels, dtype=dt)
        else:  # a chroma plane: its median
            a[:] = dt(np.median(_plane(src, dt)[:, : src.width]))
    bgr = np.ascontiguousarray(probe.to_ndarray(format="bgr24"), dtype=np.uint8)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[probe.height // 2, :levels].copy()


class Clip:
    """An open clip read by PyAV: ``decoded()`` streams (t_s, frame) from the first frame, ``grey(frame)``
    converts one (the frames not converted cost their decoding only), ``grey(frame, region)`` only the region
    a consumer reads."""

    def __init__(self, container, stream):
        self.container, self.stream = container, stream
        self.table: np.ndarray | None = None
        self._pool: FramePool | None = None  # whole frames for grey(frame, region), 0 outside the region
        self._pool_key: tuple | None = None  # ((H, W), region) the pool's frames were made for

    def decoded(self) -> Iterator:
        """(t_s, decoded frame) in presentation order; stops at a frame without a timestamp or one that fails."""
        st = self.stream
        t0, tb = st.start_time or 0, float(st.time_base)
        try:
            for fr in self.container.decode(st):
                if fr.pts is None:
                    return
                yield float(fr.pts - t0) * tb, fr
        except av.FFmpegError:  # a cut or corrupt stream: what decoded is the clip, as OpenCV's reader stops
            return

    def grey(self, frame, region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """The grey uint8 frame (H x W) of a decoded frame. ``region`` (x0, y0, x1, y1 px): only that box is
        converted, and the frame is 0 outside it, read-only and recycled (:class:`FramePool`): at 4K the
        section's box is a tenth of the frame, and the lookup of the whole frame cost more than the box's
        standardisation."""
        if self.table is None:
            self.table = grey_table(frame)
        if region is None:
            return _lookup(_luma(frame), self.table)
        x0, y0, x1, y1 = region
        shape = (frame.height, frame.width)
        if self._pool is None or self._pool_key != (shape, region):  # a recycled frame is 0 outside its own region
            self._pool, self._pool_key = FramePool(shape, pool_cap(shape, region, 1), np.uint8), (shape, region)
        luma = _luma(frame)[y0:y1, x0:x1]
        return self._pool.filled(region, lambda v: _lookup(luma, self.table, v))

    def patches(self, frame, boxes) -> tuple[np.ndarray, ...]:
        """The grey crops (uint8) of ``boxes`` ((x0, y0, x1, y1) px, inside the frame) of a decoded frame."""
        if self.table is None:
            self.table = grey_table(frame)
        luma = _luma(frame)
        return tuple(_lookup(luma[y0:y1, x0:x1], self.table) for x0, y0, x1, y1 in boxes)

    def close(self) -> None:
        self.container.close()


def usable(path: str, shape: tuple[int, int]) -> bool:
    """Whether PyAV reads ``path`` as grey here (see the module docstring); ``shape``: (H, W) of OpenCV's first
    frame, which PyAV's must match (OpenCV turns a clip by its rotation metadata)."""
    try:
        with av.open(path) as c:
            st = c.streams.video[0] if c.streams.video else None
            if st is None or not readable(st.codec_context.pix_fmt or ""):
                return False
            first = next(c.decode(st), None)
            return (
                first is not None
                and readable(first.format.name)
                and not first.rotation
                and (first.height, first.width) == tuple(shape)
                and first.pts is not None
            )
    except (av.FFmpegError, OSError, ValueError):
        return False


def deep_frame(path: str, t_s: float = 0.0, time_scale: float = 1.0) -> np.ndarray | None:
    """The BGR frame (uint8) at or just after ``t_s`` (the stream's times multiplied by ``time_scale``, as
    FrameSource's) of a clip in one of :data:`DEEP_FORMATS` without rotation, by FFmpeg's conversion; None for
    any other clip (OpenCV reads those: its BGR of a 10-bit frame costs 2 s for the first frame)."""
    try:
        with av.open(path) as c:
            st = c.streams.video[0] if c.streams.video else None
            if st is None or (st.codec_context.pix_fmt or "") not in DEEP_FORMATS:
                return None
            t0, tb, last = st.start_time or 0, float(st.time_base or 0), None
            for fr in c.decode(st):
                if fr.rotation or fr.format.name not in DEEP_FORMATS:
                    return None
                last = fr
                if fr.pts is None or float(fr.pts - t0) * tb * time_scale >= t_s - 1e-6:
                    break
            return None if last is None else np.ascontiguousarray(last.to_ndarray(format="bgr24"), dtype=np.uint8)
    except (av.FFmpegError, OSError, ValueError):
        return None


def open_clip(path: str, threads: int) -> Clip | None:
    """``path`` opened for grey decoding (:func:`usable` said so), or None when it no longer opens.
    ``threads``: decoder threads (1: the calling thread only; 0: FFmpeg's choice, all cores)."""
    try:
        c = av.open(path)
    except (av.FFmpegError, OSError, ValueError):
        return None
    st = c.streams.video[0]
    if threads != 1:
        st.thread_type = "AUTO"
        st.thread_count = threads
    return Clip(c, st)
