"""A minimal Matroska (MKV) writer for variable-frame-rate clips with exact timestamps.

OpenCV's ``VideoWriter`` writes constant-rate files only, and no muxer library (PyAV, ffmpeg) is
installed, so this writes the container directly: one video track, Motion-JPEG frames (``V_MJPEG``)
as ``SimpleBlock`` s, each with its own timestamp on a 10 µs grid. ffmpeg (hence OpenCV's reader)
decodes it and reports those timestamps through ``CAP_PROP_POS_MSEC``, as it does for a phone's
VFR recording.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

TIMECODE_SCALE_NS = 10_000  # one timestamp tick = 10 µs
_CLUSTER_TICKS = 30_000  # a new cluster every 0.3 s keeps block offsets inside int16


def _size(n: int) -> bytes:
    """EBML variable-length size of ``n`` bytes."""
    for length in range(1, 9):
        if n < (1 << (7 * length)) - 1:
            return ((1 << (7 * length)) | n).to_bytes(length, "big")
    raise ValueError("EBML element too large")


def _el(eid: bytes, payload: bytes) -> bytes:
    return eid + _size(len(payload)) + payload


def _uint(eid: bytes, v: int) -> bytes:
    return _el(eid, int(v).to_bytes(max(1, (int(v).bit_length() + 7) // 8), "big"))


def _float(eid: bytes, v: float) -> bytes:
    return _el(eid, struct.pack(">d", float(v)))


def _str(eid: bytes, v: str) -> bytes:
    return _el(eid, v.encode("ascii"))


def ticks_of(t_s: float) -> int:
    """Container ticks (10 µs) of a time in seconds; render frames at ``ticks_of(t) * 1e-5`` to be exact."""
    return int(round(t_s * 1e9 / TIMECODE_SCALE_NS))


class MkvWriter:
    """Write gray or BGR uint8 frames with explicit timestamps (s) to a Matroska MJPEG file.

    Frames are JPEG-encoded as they arrive (``quality`` 0..100); the file is written on
    :meth:`release`. Timestamps must increase.
    """

    def __init__(self, path: Path | str, size: tuple[int, int], quality: int = 95) -> None:
        self.path = Path(path)
        self.w, self.h = size
        self.quality = int(quality)
        self._clusters: list[bytes] = []
        self._blocks: list[bytes] = []
        self._cluster_tc: int | None = None
        self._last: int | None = None
        self._step = 0

    def write(self, frame: np.ndarray, t_s: float) -> None:
        tc = ticks_of(t_s)
        if self._last is not None and tc <= self._last:
            raise ValueError(f"MKV timestamps must increase ({tc} after {self._last} ticks)")
        if self._last is not None:
            self._step = tc - self._last
        self._last = tc
        if self._cluster_tc is None or tc - self._cluster_tc >= _CLUSTER_TICKS:
            self._flush()
            self._cluster_tc = tc
        ok, jpg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        if not ok:
            raise ValueError("JPEG encoding failed")
        block = b"\x81" + struct.pack(">h", tc - self._cluster_tc) + b"\x80" + jpg.tobytes()
        self._blocks.append(_el(b"\xa3", block))

    def _flush(self) -> None:
        if self._blocks:
            assert self._cluster_tc is not None  # set with the cluster's first block
            self._clusters.append(_el(b"\x1f\x43\xb6\x75", _uint(b"\xe7", self._cluster_tc) + b"".join(self._blocks)))
        self._blocks = []

    def release(self) -> None:
        self._flush()
        header = _el(
            b"\x1a\x45\xdf\xa3",
            _uint(b"\x42\x86", 1)
            + _uint(b"\x42\xf7", 1)
            + _uint(b"\x42\xf2", 4)
            + _uint(b"\x42\xf3", 8)
            + _str(b"\x42\x82", "matroska")
            + _uint(b"\x42\x87", 4)
            + _uint(b"\x42\x85", 2),
        )
        duration = float((self._last or 0) + self._step)
        info = _el(
            b"\x15\x49\xa9\x66",
            _uint(b"\x2a\xd7\xb1", TIMECODE_SCALE_NS)
            + _float(b"\x44\x89", duration)
            + _str(b"\x4d\x80", "fieldtool")
            + _str(b"\x57\x41", "fieldtool"),
        )
        video = _el(b"\xe0", _uint(b"\xb0", self.w) + _uint(b"\xba", self.h))
        track = _el(
            b"\xae", _uint(b"\xd7", 1) + _uint(b"\x73\xc5", 1) + _uint(b"\x83", 1) + _str(b"\x86", "V_MJPEG") + video
        )
        segment = _el(b"\x18\x53\x80\x67", info + _el(b"\x16\x54\xae\x6b", track) + b"".join(self._clusters))
        self.path.write_bytes(header + segment)
        self._clusters = []
