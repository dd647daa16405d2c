"""What a clip says about itself, for the report and the standard outputs.

The recording date/time is read from the container, without ffprobe (not always installed):

- MP4/MOV/3GP: the ``moov/mvhd`` creation time (seconds since 1904-01-01 UTC), read by
  :func:`fieldtool.records.history.video_datetime`;
- Matroska/WebM (MKV): the ``Segment/Info/DateUTC`` element (nanoseconds since 2001-01-01 UTC).

When the container carries no date, the file's modification time is given instead and the
source says so ("file mtime"). Frame size, frame rate, frame count and duration come from the
frame reader (OpenCV's view of the container), as the run used them.
"""

from __future__ import annotations

import struct
from datetime import UTC, datetime, timedelta
from pathlib import Path

from fieldtool.records.history import _iso, video_datetime

_MKV_EPOCH = datetime(2001, 1, 1, tzinfo=UTC)
_EBML_MAGIC = b"\x1a\x45\xdf\xa3"
_SEGMENT, _INFO, _DATE_UTC = 0x18538067, 0x1549A966, 0x4461
_CLUSTER = 0x1F43B675


def _vint(fh, keep_marker: bool) -> tuple[int, int] | None:
    """One EBML variable-length integer: (value, length in bytes), or None at the end of the file."""
    b = fh.read(1)
    if not b:
        return None
    first = b[0]
    length = next((i + 1 for i in range(8) if first & (0x80 >> i)), 0)
    if length == 0:
        return None
    rest = fh.read(length - 1)
    if len(rest) < length - 1:
        return None
    value = first if keep_marker else first & (0xFF >> length)
    for c in rest:
        value = (value << 8) | c
    if not keep_marker and value == (1 << (7 * length)) - 1:
        value = -1  # "unknown size"
    return value, length


def mkv_creation_time(path: Path | str, max_elements: int = 4096) -> datetime | None:
    """``DateUTC`` of a Matroska/WebM file, or None when absent. Reads element headers only."""
    try:
        with Path(path).open("rb") as fh:
            if fh.read(4) != _EBML_MAGIC:
                return None
            fh.seek(0)
            end = Path(path).stat().st_size
            stack_end = end
            for _ in range(max_elements):
                pos = fh.tell()
                if pos >= stack_end:
                    return None
                eid_read = _vint(fh, keep_marker=True)
                size_read = _vint(fh, keep_marker=False)
                if eid_read is None or size_read is None:
                    return None
                eid, size = eid_read[0], size_read[0]
                if eid in (_SEGMENT, _INFO):  # descend into the master elements on the way to DateUTC
                    stack_end = end if size < 0 else min(end, fh.tell() + size)
                    continue
                if eid == _DATE_UTC and size == 8:
                    ns = struct.unpack(">q", fh.read(8))[0]
                    return _MKV_EPOCH + timedelta(microseconds=ns // 1000)
                if eid == _CLUSTER or size < 0:
                    return None  # past the header: the date is not there
                fh.seek(size, 1)
    except (OSError, struct.error, OverflowError):
        return None
    return None


def recording_time(video: Path | str) -> tuple[str | None, str | None]:
    """(ISO 8601 UTC text, source) of when a clip was recorded; source is "container" or "file mtime"."""
    p = Path(video)
    if p.is_file() and p.suffix.lower() in (".mkv", ".webm", ".mka"):
        dt = mkv_creation_time(p)
        if dt is not None:
            return _iso(dt), "container"
    return video_datetime(p)


def video_info(project, source) -> dict:
    """The ``video`` entry of ``result.json``: file name, recording time, size, rate, duration.

    ``source`` is the run's :class:`~fieldtool.processing.frames.FrameSource`.
    """
    info = source.info
    path = project.resolve(project.video.path)
    when, where = recording_time(path)
    return {
        "file": Path(project.video.path).name or str(path),
        "recorded_utc": when,
        "recorded_source": where,
        "width_px": int(info.width),
        "height_px": int(info.height),
        "fps": float(info.fps),  # the filming's rate (processing/frames.py filming_clock)
        "time_scale": float(getattr(source, "time_scale", 1.0)),  # the filming's seconds per second of the file's
        "n_frames": int(info.n_frames),
        "duration_s": float(info.duration_s),
        "is_sequence": bool(info.is_sequence),
        "start_s": float(source.start_s),
        "end_s": None if source.end_s is None else float(source.end_s),
    }
