"""Stage 4, the frames: the clip as a stream of working frames (undistorted by the lens model, stabilised on
the first frame, filtered inside the ROI), with the count of identical consecutive frames on the way and
the decoder's count of frames as a plan for the ensemble.

``working_frames(want=...)`` lets a consumer skip the conversion of frames it does not read: the fast path's
rounds of pairs (run/piv_rounds.py) and the standardisation window (processing/surface.py) build only the
frames of their pairs."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import cv2
import numpy as np

from fieldtool.errors import Cancelled
from fieldtool.processing.filters import FilterStack
from fieldtool.processing.stabilize import Stabilizer
from fieldtool.project.model import Project
from fieldtool.run.clip_pass import DecodeCount
from fieldtool.run.geometry import roi_and_mask
from fieldtool.run.inputs import Inputs
from fieldtool.run.observer import Guarded, Progress


def in_region_ok(project: Project, inputs: Inputs, observer: Guarded | None) -> bool:
    """Whether raw frames may be converted only in the box their consumers read: no step reads the whole
    frame (the lens model, the stabilisation, filters, a live observer, which logs frames)."""
    return (
        inputs.lens is None
        and not project.stabilize.enabled
        and not project.filters
        and not (observer is not None and observer.active)
    )


def make_stabilizer(project: Project, inputs: Inputs, reference) -> Stabilizer:
    """The registration of ``[stabilize]`` on its first working frame ``reference`` (undistorted): the regions and
    the water polygon, picked on raw frames, moved onto the working image; the ROI (working image) as the water that
    the drift check's vote leaves out."""
    st = project.stabilize
    regions = [inputs.to_working([[r[0], r[1]], [r[2], r[3]]]).ravel().tolist() for r in st.regions_px]
    poly = inputs.to_working(st.water_polygon_px).tolist() if st.water_polygon_px else None
    roi, _ = roi_and_mask(project, inputs)  # the PIV's region: water, left out of the drift check's vote
    return Stabilizer(
        reference,
        regions_px=regions or None,
        water_polygon_px=poly,
        model=st.model,
        max_drift_px=st.max_drift_px,
        water_box_px=roi,
    )


def working_frames(
    project: Project,
    inputs: Inputs,
    cancel: Callable[[], bool] | None = None,
    observer: Guarded | None = None,
    stab_report: dict | None = None,
    progress: Progress | None = None,
    stage: str = "frames",
    want: Callable[[int], bool] | None = None,
    raw: bool = False,
    count: DecodeCount | None = None,
    region: tuple[int, int, int, int] | None = None,
) -> Iterator[tuple[float, np.ndarray]]:
    """Stream (t_s, float32 working frame): undistorted, stabilised, filtered.

    ``raw``: without filters, the frames keep the decoder's uint8 (for consumers that convert only what they
    read: the standardisation's box, STIV's lines).

    ``want(k)``: frames at stream positions k that fail it come as (t_s, None), decoded past but not converted
    (the fast path's rounds need only their own pairs' frames). Ignored with stabilisation, which tracks every
    frame, and with a filter stack marked ``temporal``.

    ``count``: every frame the decoder delivers is counted in ``count.frames`` (a filter's prepass too).

    ``region`` (x0, y0, x1, y1 px), with ``raw``: the consumers read only this box, so the decoder converts only
    it (the frames are 0 outside it, read-only; processing/frames.py). Ignored where a step reads the whole
    frame: the lens model, the stabilisation, filters, a live observer (it logs frames)."""
    # filters work inside the ROI only (thesis 9.2.7): banks and sky do not set their statistics
    stack = FilterStack.from_config(project.filters, roi=roi_and_mask(project, inputs)[0]) if project.filters else None
    every = observer is not None and observer.wants_every_frame()  # the overlay video draws every frame
    if project.stabilize.enabled or getattr(stack, "temporal", False) or every:
        want = None
    stabilizer = None
    total = inputs.source.estimated_count()
    region = region if raw and in_region_ok(project, inputs, observer) else None

    def corrected() -> Iterator[tuple[int, float, np.ndarray]]:
        nonlocal stabilizer
        for fr in inputs.source if want is None and region is None else inputs.source.iter_wanted(want, region):
            if count is not None:
                count.frames += 1
            img = fr.image
            if img is None:
                yield fr.index, fr.t_s, None
                continue
            if inputs.lens is not None:
                img = inputs.lens.undistort(img)
            if project.stabilize.enabled:
                if stabilizer is None:
                    stabilizer = make_stabilizer(project, inputs, img)
                else:
                    img = stabilizer.register(img)
            yield fr.index, fr.t_s, img

    if stack is not None and stack.needs_prepass:
        want, want_later = None, want
        stack.prepass(img for _, _, img in corrected())
        want = want_later
        stabilizer = None  # registered again on the second pass, identically
    log_every = max(1, total // 20) if total else 10
    for k, (idx, t, img) in enumerate(corrected()):
        if cancel is not None and cancel():
            raise Cancelled("cancelled by the user")
        if img is None:
            if progress is not None:
                progress(stage, k + 1, total)
            yield t, None
            continue
        out = stack.apply(img) if stack is not None else img if raw else img.astype(np.float32)
        if observer is not None and k % log_every == 0:
            observer("frame", idx, t, img, out)
        if every and observer is not None:  # every implies an observer
            observer("every_frame", idx, t, img)
        if progress is not None:
            progress(stage, k + 1, total)
        yield t, out
    if every and observer is not None:
        observer("frames_done")
    if stab_report is not None and stabilizer is not None:
        stab_report.update(stabilizer.report())


def count_identical(frames: Iterator[tuple[float, np.ndarray]], stats: dict) -> Iterator[tuple[float, np.ndarray]]:
    """Pass the frames through, counting consecutive frames that are identical (duplicates, a still image):
    every fourth row compared (its largest difference under half a grey level), in one pass of
    ``cv2.norm``. The previous frame is held, not copied: a decoded or corrected frame is a new array that
    nothing writes after it is passed on."""
    prev = None
    n = same = 0
    for t, img in frames:
        if img is None:  # a frame the fast path did not decode (working_frames(want=...))
            yield t, img
            continue
        if prev is not None:
            n += 1
            if (
                prev.shape == img.shape
                and prev.dtype == img.dtype
                and cv2.norm(img[::4], prev[::4], cv2.NORM_INF) < 0.5
            ):
                same += 1
        prev = img
        stats["pairs"], stats["identical"] = n, same
        yield t, img


class Sized:
    """A frame stream with the count the container claims (a plan, not a promise: it may end sooner)."""

    def __init__(self, frames: Iterator, n: int):
        self.frames, self.n = frames, n

    def __iter__(self) -> Iterator:
        return iter(self.frames)

    def __len__(self) -> int:
        return self.n
