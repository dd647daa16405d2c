"""Frames of a clip: any video OpenCV/ffmpeg reads, or an image sequence (folder or glob).

Frames are streamed one at a time as :class:`Frame` (index in the clip, time in seconds, gray
uint8 image). Times come from the container's timestamps; image sequences use the frame interval
the user gives. Nothing here keeps more than one frame in memory.

Times are the filming's seconds. A slow-motion or time-lapse clip plays at another rate than it was filmed at: a
phone filming 240 frames a second writes them 1/30 s apart and the rate it filmed at in the tag
:data:`CAPTURE_TAG`. :func:`filming_clock` reads it (or ``video.capture_fps``), and every time here, ``start_s``
and ``end_s`` included, is then the container's time multiplied by ``time_scale`` (= the file's rate / the
filming rate): a velocity is metres per second of the river's, not of the playback's.
"""

from __future__ import annotations

import os
import re
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from itertools import islice
from pathlib import Path
from typing import NamedTuple

import av
import cv2
import numpy as np

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing import video_av
from fieldtool.processing.paths import is_pattern, literal_glob

#: (x0, y0, x1, y1) px, a box of the frame
Box = tuple[int, int, int, int]

#: the container tag where a phone writes the rate a slow-motion or time-lapse clip was filmed at (frames/s;
#: Android's MediaRecorder, in MP4's metadata)
CAPTURE_TAG = "com.android.capture.fps"
#: a tagged filming rate within this share of the file's own rate is the file's rate (29.97 against 30)
SAME_RATE = 0.01

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp"}

#: decoder threads (OpenCV's CAP_PROP_N_THREADS): 1 on two cores or fewer, else FFmpeg's choice (0)
_DECODER_THREADS = (
    1 if (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)) <= 2 else 0
)


class Frame(NamedTuple):
    index: int  # position in the clip (0-based, before the step is applied)
    t_s: float  # time from the start of the clip (s)
    image: np.ndarray  # gray uint8, H x W


@dataclass(frozen=True)
class ClipInfo:
    """What the file says about itself. ``duration_s`` is the container's estimate."""

    path: str
    width: int
    height: int
    fps: float  # nominal frames per second (s⁻¹); for sequences 1 / frame_interval_s
    n_frames: int  # as claimed by the container (may exceed what decodes)
    duration_s: float
    is_sequence: bool


def _inside(region: Box | None, outer: Box | None) -> bool:
    """Whether frames right inside ``outer`` (None: everywhere) are right inside ``region`` (None: everywhere)."""
    if outer is None:
        return True
    if region is None:
        return False
    return outer[0] <= region[0] and outer[1] <= region[1] and region[2] <= outer[2] and region[3] <= outer[3]


def _crops(img: np.ndarray, boxes) -> tuple[np.ndarray, ...]:
    """Copies of the ``boxes`` (x0, y0, x1, y1 px) of a whole grey frame (``FrameSource.watch``)."""
    return tuple(img[y0:y1, x0:x1].copy() for x0, y0, x1, y1 in boxes)


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


def sequence_files(path: Path) -> list[Path] | None:
    """Image files of a sequence given as a folder or a glob; None when ``path`` is a video."""
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTS]
    elif is_pattern(path):
        files = [Path(p) for p in literal_glob(path) if Path(p).suffix.lower() in IMAGE_EXTS]
    else:
        return None
    return sorted(files, key=_natural_key)


_END_MARKERS = {
    ".jpg": (b"\xff\xd9", "JPEG end marker"),
    ".jpeg": (b"\xff\xd9", "JPEG end marker"),
    ".png": (b"IEND", "PNG end chunk"),
}
_TAIL_BYTES = 1024  # an end marker is searched in the last KiB (cameras may pad after it)


def cut_short(path: Path) -> str | None:
    """Why an image file of a sequence is cut short (a JPEG without its end marker, a PNG without its end
    chunk: a copy or upload that stopped midway), or None. Reads the file's last KiB only."""
    marker = _END_MARKERS.get(path.suffix.lower())
    if marker is None:
        return None
    try:
        with open(path, "rb") as fh:
            size = fh.seek(0, os.SEEK_END)
            fh.seek(max(0, size - _TAIL_BYTES))
            tail = fh.read()
    except OSError as e:
        return f"{path}: cannot be read ({e.strerror})"
    if marker[0] in tail:
        return None
    return (
        f"{path}: the image is cut short (no {marker[1]}; a copy that stopped midway); copy it again or "
        "remove it from the sequence"
    )


class FrameSource:
    """A clip with a time range and a step, iterable as :class:`Frame` objects.

    Parameters
    ----------
    path : video file, folder of images, or glob pattern.
    start_s, end_s : time range in seconds (``end_s`` None = to the end).
    step : keep every ``step``-th frame (>= 1).
    frame_interval_s : image sequences only, time between two images (s).
    capture_fps : videos only, the rate the clip was filmed at (frames/s; None: the file's :data:`CAPTURE_TAG`,
        else its own rate). ``time_scale`` and ``clock_said`` are :func:`filming_clock`'s.
    """

    def __init__(
        self,
        path: Path | str,
        start_s: float = 0.0,
        end_s: float | None = None,
        step: int = 1,
        frame_interval_s: float | None = None,
        capture_fps: float | None = None,
    ) -> None:
        self.path = Path(path)
        self.files = sequence_files(self.path)
        if step < 1:
            raise ParameterError(f"video.step: {step} is not allowed; use 1 (every frame) or more")
        self.time_scale, self.clock_said = 1.0, None
        if self.files is None:
            info = self._probe_video()
            clock = filming_clock(self.path, info.fps, capture_fps)
            self.time_scale, self.clock_said = clock.scale, clock.said
            self.info = (
                info
                if clock.scale == 1.0
                else ClipInfo(
                    info.path, info.width, info.height, clock.fps, info.n_frames, info.duration_s * clock.scale, False
                )
            )
        elif capture_fps is not None:
            raise ParameterError(
                "video.capture_fps: an image sequence's clock is video.frame_interval_s; leave capture_fps unset"
            )
        else:
            if not self.files:
                raise InputFileError(f"{self.path}: no images ({', '.join(sorted(IMAGE_EXTS))}) found")
            for f in self.files:  # before any decoding: libjpeg would print its own lines for a cut image
                msg = cut_short(f)
                if msg:
                    raise InputFileError(msg)
            if frame_interval_s is None or not frame_interval_s > 0:
                raise ParameterError(
                    "video.frame_interval_s: an image sequence carries no timestamps; give the time between two "
                    "images in seconds"
                )
            first = cv2.imread(str(self.files[0]), cv2.IMREAD_GRAYSCALE)
            if first is None:
                raise InputFileError(f"{self.files[0]}: cannot be read as an image")
            n = len(self.files)
            self.info = ClipInfo(
                str(self.path), first.shape[1], first.shape[0], 1.0 / frame_interval_s, n, n * frame_interval_s, True
            )
        self.frame_interval_s = frame_interval_s
        dur = self.info.duration_s
        if start_s < 0 or (dur > 0 and start_s >= dur):
            raise ParameterError(f"video.start_s: {start_s:g} s is outside the clip (0 to {dur:.2f} s)")
        if end_s is not None:
            if end_s <= start_s:
                raise ParameterError(f"video.end_s: {end_s:g} s must be after video.start_s ({start_s:g} s)")
            if dur > 0 and end_s > dur + 1.0 / max(self.info.fps, 1e-9):
                raise ParameterError(f"video.end_s: {end_s:g} s is beyond the end of the clip ({dur:.2f} s)")
        self.start_s, self.end_s, self.step = float(start_s), end_s, int(step)
        self._head: tuple[deque, Iterator[Frame], Box | None] | None = None  # see head()
        self._av: bool | None = None  # PyAV reads the clip as grey (processing/video_av.py); None: not probed
        self._watch: tuple | None = None  # see watch()
        self.watched: dict[int, tuple[float, tuple]] = {}

    def _probe_video(self) -> ClipInfo:
        if not self.path.exists():
            raise InputFileError(f"{self.path}: video not found; check video.path in the project file")
        cap = cv2.VideoCapture(str(self.path))
        try:
            ok = cap.grab() if cap.isOpened() else False
            frame = video_av.deep_frame(str(self.path)) if ok else None  # a 10-bit clip: not OpenCV's BGR
            if ok and frame is None:
                ok, frame = cap.retrieve()
            if not ok:
                raise InputFileError(f"{self.path}: cannot be read as a video (unknown format or corrupt file)")
            fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        finally:
            cap.release()
        assert frame is not None  # read ok
        h, w = frame.shape[:2]
        dur = n / fps if fps > 0 and n > 0 else 0.0
        return ClipInfo(str(self.path), w, h, float(fps), n, dur, False)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of a frame in pixels."""
        return self.info.height, self.info.width

    def estimated_count(self) -> int:
        """Number of frames the iteration should yield (from the container's claims)."""
        dur = self.info.duration_s
        end = dur if self.end_s is None else min(self.end_s, dur) if dur > 0 else self.end_s
        if end is None or self.info.fps <= 0:
            return 0
        n = int(round((end - self.start_s) * self.info.fps))
        return max(0, (n + self.step - 1) // self.step)

    def __iter__(self) -> Iterator[Frame]:
        return self._stream(None)

    def iter_wanted(self, want, region: Box | None = None) -> Iterator[Frame]:
        """As iteration, but a frame whose position in the stream (0-based, after the step) fails ``want(k)`` is
        only decoded past (video: grabbed, not retrieved; sequence: not read) and comes with ``image = None``.
        ``region`` (x0, y0, x1, y1 px): the frames are right inside it only, read-only, and may be 0 outside
        (PyAV converts only the region to grey; processing/video_av.py)."""
        return self._stream(want, region)

    def head(self, n: int, region: Box | None = None) -> list[Frame]:
        """The first ``n`` frames of the range (fewer in a shorter clip). A video's next pass replays them and
        continues the decoder that read them, so that a look at the first frames (run/clip_check.py) costs no
        decoding of its own; the frames must not be written into. ``region`` as in :meth:`iter_wanted`: the
        next pass continues this one only if it asks for a region inside this one. A second call for a region
        inside the first's takes the frames the first read, without decoding them again."""
        if self.files is not None:
            return list(islice(self._iter_sequence(), n))
        held = self._head
        if held is not None and _inside(region, held[2]) and len(held[0]) >= n:
            return list(islice(held[0], n))
        if held is not None:
            held[1].close()
        rest = self._iter_video(region=region)
        got = list(islice(rest, n))
        self._head = (deque(got), rest, region)
        return got

    def thin(self, factor: int) -> None:
        """From now on keep every ``factor``-th frame of those kept so far (the step multiplied). The frames
        :meth:`head` holds are thinned the same way, so the next pass still replays them and continues their
        decoder (its frames keep their positions in the range: the kept ones are the multiples of the new step).
        A :meth:`watch` is re-counted in the new step's frames: the patches kept so far at the frames still kept,
        and its ``first`` and ``every`` divided by ``factor`` (rounded up), so that it keeps as many patches over
        the clip's seconds as before."""
        factor = int(factor)
        if factor <= 1:
            return
        if self._head is not None:
            held, rest, region = self._head
            self._head = (deque(list(held)[::factor]), rest, region)
        if self._watch is not None:
            boxes, first, every = self._watch
            self._watch = (boxes, -(-first // factor), max(1, -(-every // factor)))
            self.watched = {k // factor: v for k, v in self.watched.items() if k % factor == 0}
        self.step *= factor

    def watch(self, boxes: list[Box] | None, first: int = 0, every: int = 1) -> None:
        """From now on, every pass that decodes the frame at stream position k keeps the grey crops (uint8) of
        ``boxes`` (x0, y0, x1, y1 px, inside the frame) for k < ``first`` and every ``every``-th k after, wherever
        its region is: ``watched[k] = (t_s, crops)`` (the camera check's patches around the GCPs, run/camera.py;
        the same crops whichever pass decoded them). None: no more."""
        self._watch = (tuple(boxes), int(first), max(1, int(every))) if boxes else None
        self.watched = {}

    @property
    def watch_first(self) -> int:
        """The ``first`` of the :meth:`watch` on (in the frames of the current step; 0 when none is)."""
        return self._watch[1] if self._watch is not None else 0

    def _watched(self, k: int) -> tuple | None:
        """The boxes to keep at stream position ``k``, or None."""
        w = self._watch
        return w[0] if w is not None and (k < w[1] or k % w[2] == 0) else None

    def __getstate__(self) -> dict:
        """A copy for another process (the figure process gets the run's inputs as a pickle) without the open
        decoder of :meth:`head`: its iteration starts a pass of its own."""
        state = self.__dict__.copy()
        state["_head"] = None
        state["_watch"], state["watched"] = None, {}
        return state

    def _stream(self, want, region: Box | None = None) -> Iterator[Frame]:
        if self.files is not None:
            return self._iter_sequence(want)
        head, self._head = self._head, None
        if head is not None and _inside(region, head[2]):
            return self._resumed(head[0], head[1], want)
        if head is not None:
            head[1].close()
        return self._iter_video(want, region)

    @staticmethod
    def _resumed(frames: deque, rest: Iterator[Frame], want) -> Iterator[Frame]:
        """The head's frames (dropped as they go), then the rest of their pass; ``want`` as in iter_wanted."""
        k = 0
        try:
            while frames:
                f = frames.popleft()
                yield f if want is None or want(k) else f._replace(image=None)
                k += 1
            for f in rest:
                yield f if want is None or want(k) else f._replace(image=None)
                k += 1
        finally:
            close = getattr(rest, "close", None)
            if close is not None:
                close()

    def _in_range(self, t: float) -> int:
        """-1 before the range, 0 inside, 1 after."""
        eps = 1e-6
        if t < self.start_s - eps:
            return -1
        if self.end_s is not None and t > self.end_s + eps:
            return 1
        return 0

    def _iter_sequence(self, want=None) -> Iterator[Frame]:
        assert self.files is not None and self.frame_interval_s is not None  # an image sequence has both
        kept = 0
        for i, f in enumerate(self.files):
            t = i * self.frame_interval_s
            where = self._in_range(t)
            if where < 0:
                continue
            if where > 0:
                break
            if kept % self.step == 0 and want is not None and not want(kept // self.step):
                yield Frame(i, t, None)
            elif kept % self.step == 0:
                img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                if img is None:
                    raise InputFileError(f"{f}: cannot be read as an image")
                if img.shape != self.shape:
                    raise InputFileError(f"{f}: size {img.shape[1]}x{img.shape[0]} differs from the first image")
                boxes = self._watched(kept // self.step)
                if boxes:
                    self.watched[kept // self.step] = (t, _crops(img, boxes))
                yield Frame(i, t, img)
            kept += 1

    def _iter_video(self, want=None, region: Box | None = None) -> Iterator[Frame]:
        # the run already keeps two cores busy (decoding, standardising, correlating: one thread each); on two
        # cores or fewer the decoder's own threads only compete with them
        if self._av is None:
            self._av = video_av.usable(str(self.path), self.shape)
        clip = video_av.open_clip(str(self.path), _DECODER_THREADS) if self._av else None
        if clip is None:
            decoded = self._decoded_cv()
        else:  # region: only the box a consumer reads is converted (video_av.Clip.grey)
            grey_of = partial(clip.grey, region=region)
            decoded = ((t, fr, grey_of) for t, fr in clip.decoded())
        try:
            kept = 0
            scale = self.time_scale
            for i, (t, fr, grey) in enumerate(decoded):
                t *= scale  # the filming's seconds
                where = self._in_range(t)
                if where < 0:
                    continue
                if where > 0:
                    return
                k, off = divmod(kept, self.step)
                on_step = off == 0
                boxes = self._watched(k) if on_step else None
                if boxes and clip is not None:  # PyAV: the crops of a decoded frame, converted or not
                    self.watched[k] = (t, clip.patches(fr, boxes))
                if on_step and want is not None and not want(k):
                    yield Frame(i, t, None)
                elif on_step:
                    img = grey(fr)
                    if img is None:
                        return
                    if boxes and clip is None:  # OpenCV's reader: the whole grey frame
                        self.watched[k] = (t, _crops(img, boxes))
                    yield Frame(i, t, img)
                kept += 1
        finally:
            decoded.close()
            if clip is not None:
                clip.close()

    def _decoded_cv(self) -> Iterator:
        """OpenCV's reader (clips PyAV does not read as grey, processing/video_av.py): (t_s, capture, grey)
        for every frame grabbed, ``grey(capture)`` its grey frame or None."""
        cap = cv2.VideoCapture(str(self.path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, _DECODER_THREADS])
        bgr = None  # the decoder's colour frame, one buffer for the clip (only the grey copy leaves)

        def grey(c):
            nonlocal bgr
            ok, img = c.retrieve(bgr)
            if not ok:
                return None
            if img.ndim == 3:
                bgr = img
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            return img

        try:
            while cap.grab():
                yield cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0, cap, grey
        finally:
            cap.release()


class Clock(NamedTuple):
    """A video's clock (:func:`filming_clock`): its times multiplied by ``scale`` are the filming's seconds, at
    ``fps`` frames per second of filming; ``said``: the sentence that says so (None where the scale is 1)."""

    scale: float
    fps: float
    said: str | None


def filming_clock(path: Path | str, file_fps: float, capture_fps: float | None = None) -> Clock:
    """The :class:`Clock` of a video whose own rate is ``file_fps`` (frames/s, OpenCV's; FFmpeg's
    guess from the stream's timestamps where PyAV reads one): the filming's seconds are the file's times the
    scale. The filming rate is ``capture_fps`` (the key ``video.capture_fps``), else the file's
    :data:`CAPTURE_TAG` unless it is within :data:`SAME_RATE` of the file's rate; with neither the scale is 1
    and nothing is said."""
    tagged, guessed = _clip_rates(path)
    file_fps = guessed or file_fps
    rate, where = capture_fps, "video.capture_fps"
    if rate is None:
        rate, where = tagged, f"the file's {CAPTURE_TAG} tag"
        if rate is None or not file_fps > 0 or abs(rate / file_fps - 1.0) <= SAME_RATE:
            return Clock(1.0, file_fps, None)
    elif not file_fps > 0:
        raise ParameterError(
            f"video.capture_fps: {path} gives no frame rate of its own to set the filming's apart from; leave "
            "capture_fps unset"
        )
    scale = file_fps / rate
    if scale == 1.0:
        return Clock(1.0, file_fps, None)
    kind = "slow motion" if scale < 1 else "time-lapse"
    return Clock(
        scale,
        rate,
        (
            f"filmed at {rate:g} frames per second ({where}) and played at {file_fps:g} ({kind}): a frame is "
            f"1/{rate:g} s of the river's, and the clip's times (video.start_s, video.end_s, the outputs') are the "
            f"filming's seconds, "
            f"{scale:g} x the player's"
        ),
    )


def _clip_rates(path: Path | str) -> tuple[float | None, float | None]:
    """(the file's :data:`CAPTURE_TAG`, FFmpeg's guess of its video stream's rate), frames/s; None where absent,
    not a positive number, or unreadable."""

    def positive(v) -> float | None:
        try:
            f = float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return f if np.isfinite(f) and f > 0 else None

    try:
        with av.open(str(path), metadata_errors="ignore") as c:
            video = c.streams.video
            tags = {**(video[0].metadata if video else {}), **c.metadata}
            guessed = positive(video[0].guessed_rate) if video else None
    except (av.error.FFmpegError, OSError, ValueError, UnicodeDecodeError):
        return None, None
    return positive(tags.get(CAPTURE_TAG)), guessed


def read_color_frame(
    path: Path | str, t_s: float = 0.0, frame_interval_s: float | None = None, capture_fps: float | None = None
) -> np.ndarray:
    """The BGR frame at (or just after) ``t_s`` seconds, for display and plots (a video's seconds are the
    filming's, as FrameSource's: ``capture_fps`` as there)."""
    path = Path(path)
    files = sequence_files(path)
    if files is not None:
        if not files:
            raise InputFileError(f"{path}: no images found")
        idx = int(round(t_s / frame_interval_s)) if frame_interval_s else 0
        img = cv2.imread(str(files[min(idx, len(files) - 1)]), cv2.IMREAD_COLOR)
        if img is None:
            raise InputFileError(f"{files[idx]}: cannot be read as an image")
        return img
    if not path.exists():
        raise InputFileError(f"{path}: video not found; check video.path in the project file")
    cap = cv2.VideoCapture(str(path))
    try:
        scale = filming_clock(path, cap.get(cv2.CAP_PROP_FPS) or 0.0, capture_fps).scale if t_s > 0 else 1.0
        last = video_av.deep_frame(str(path), t_s, scale)  # a 10-bit clip: FFmpeg's BGR, as its grey frames
        if last is not None:
            return last
        while cap.grab():
            ok, img = cap.retrieve()
            if ok:
                last = img
            if cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0 * scale >= t_s - 1e-6:
                break
    finally:
        cap.release()
    if last is None:
        raise InputFileError(f"{path}: cannot be read as a video (unknown format or corrupt file)")
    return last
