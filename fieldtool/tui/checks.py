"""Whether each step's entries are right, for the sidebar marks and the "next" key.

Three layers, cheapest first: the TUI's own field checks (``fields.field_errors``) and the
project's validation layer (``fieldtool.project.validation`` through ``steps.step_problems``), both in
``Session.step_errors``; then the core's own check of the step (``core_check``: it reads the clip,
builds the cross-section, solves the GCPs, computes a typed level), which catches what needs the
files and the other steps: a start past the end
of the clip, a level below the bed, a CSV given as the video. Core checks are cached on the project
tables they depend on, so the sidebar can be refreshed after every keystroke.
"""

from __future__ import annotations

import json

from fieldtool.errors import FieldToolError, ParameterError
from fieldtool.processing import piv as piv_mod
from fieldtool.processing.calibration import load_calibration
from fieldtool.processing.filters import FilterStack
from fieldtool.processing.frames import FrameSource, read_color_frame
from fieldtool.project.model import project_to_dict
from fieldtool.run.geometry import build_mapping, build_section, level_and_mapping, roi_and_mask
from fieldtool.run.inputs import load_cross_section
from fieldtool.run.velocimetry import piv_params

# project tables each step's core check reads (its cache key)
_INPUTS = ("video", "cross_section", "calibration")
CORE_TABLES = {
    "cross_section": ("cross_section",),
    "video": ("video", "stabilize"),
    "calibration": ("calibration",),
    "ortho": _INPUTS + ("ortho",),
    "water_level": _INPUTS + ("ortho", "water_level"),
    "roi": _INPUTS + ("roi",),
    "filters": ("filters",),
    "piv": _INPUTS + ("roi", "piv"),
    "section": _INPUTS + ("ortho", "water_level", "section"),
}


def core_check(session, step: str) -> None:
    """The core's check of ``step`` on the session's project; raises FieldToolError with the message."""
    p = session.project
    if step == "cross_section":
        load_cross_section(p)
    elif step == "video":  # the clip alone (not the lens, whose step comes after)
        v = p.video
        if not v.path:
            raise ParameterError("video.path: no video given; set the clip to analyse")
        src = FrameSource(p.resolve(v.path), v.start_s, v.end_s, v.step, v.frame_interval_s, v.capture_fps)
        read_color_frame(p.resolve(v.path), v.start_s, v.frame_interval_s, v.capture_fps)
        if src.estimated_count() < 2:
            raise ParameterError(
                "video: the range holds fewer than 2 frames; widen video.start_s .. video.end_s or lower video.step"
            )
    elif step == "calibration":
        if session.ui.get("calibration_mode") != "skip" and p.calibration.path:
            load_calibration(p.resolve(p.calibration.path))
    elif step == "ortho":
        if p.ortho.method in ("distances", "world", "two_points"):
            build_mapping(p, session.inputs(), None)
        elif p.ortho.method == "pose" and not p.calibration.path:
            raise ParameterError("ortho.method = pose needs the camera intrinsics: calibrate or load a lens in step 3")
    elif step == "water_level":
        level_and_mapping(p, session.inputs())
    elif step == "roi":
        roi_and_mask(p, session.inputs())
    elif step == "filters":
        FilterStack.from_config(p.filters)
    elif step == "piv":
        inputs = session.inputs()
        roi, _ = roi_and_mask(p, inputs)
        piv_mod.check_params(inputs.shape, piv_params(p), roi)
    elif step == "section":
        section_geometry(session)


def section_geometry(session):
    """(section geometry, level result, cross-section) of the session's project, with the same
    checks as `fieldtool run` (``run.geometry.build_section``)."""
    p = session.project
    inputs = session.inputs()
    level, mapping = level_and_mapping(p, inputs)
    geom = build_section(p, inputs, level.level_m, mapping)
    return geom, level, inputs.cross_section


class CoreChecks:
    """``core_check`` results cached on the tables each step reads."""

    def __init__(self) -> None:
        self._cache: dict[str, tuple[str, str | None]] = {}

    def message(self, session, step: str) -> str | None:
        """The core check's message for ``step``, or None when it passes (or the step has none)."""
        tables = CORE_TABLES.get(step)
        if tables is None:
            return None
        d = project_to_dict(session.project)
        key = json.dumps([d.get(t) for t in tables] + [session.ui.get("calibration_mode")], sort_keys=True, default=str)
        hit = self._cache.get(step)
        if hit is not None and hit[0] == key:
            return hit[1]
        try:
            core_check(session, step)
            msg = None
        except FieldToolError as e:
            msg = str(e)
        self._cache[step] = (key, msg)
        return msg


def is_missing(message: str) -> bool:
    """Whether a field message only says an entry is still to be made (not that it is wrong)."""
    return ": required" in message or message.endswith("required")
