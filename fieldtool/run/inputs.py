"""Stage 1, the inputs: the cross-section, the clip (a :class:`FrameSource` over the selected range), the
optional lens model and the first colour frame, loaded and checked (a bad file or key raises a
FieldToolError naming it)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing import cross_section as xs
from fieldtool.processing.calibration import LensModel, load_calibration
from fieldtool.processing.frames import FrameSource, read_color_frame
from fieldtool.project.model import Project
from fieldtool.project.validation import path_problem


@dataclass
class Inputs:
    """Loaded inputs: cross-section, clip, optional lens model, and the working first frame."""

    cross_section: xs.CrossSection
    source: FrameSource
    lens: LensModel | None
    first_color: np.ndarray  # BGR raw first frame of the range

    def to_working(self, pts) -> np.ndarray:
        """Raw-frame pixels -> working-image pixels (undistorted when a lens model is given)."""
        p = np.asarray(pts, float).reshape(-1, 2)
        return self.lens.undistort_points(p) if self.lens is not None and len(p) else p

    @property
    def shape(self) -> tuple[int, int]:
        return self.source.shape


def load_cross_section(project: Project) -> xs.CrossSection:
    """The project's cross-section, from its shape or its file."""
    c = project.cross_section
    if c.shape:
        return xs.from_shape(
            c.shape,
            top_width_m=c.top_width_m,
            bottom_width_m=c.bottom_width_m,
            depth_m=c.depth_m,
            left_station_m=c.left_station_m,
            bank_elevation_m=c.bank_elevation_m,
            points=c.points,
        )
    if not c.path:
        raise ParameterError("cross_section.path: no cross-section given; set a CSV file or a shape")
    return xs.load_cross_section(project.resolve(c.path))


def load_inputs(project: Project) -> Inputs:
    """Cross-section, clip and lens model of a project, checked."""
    cs = load_cross_section(project)
    v = project.video
    if not v.path:
        raise ParameterError("video.path: no video given; set the clip to analyse")
    msg = path_problem(project.resolve(v.path), "video.path", kind="video")  # a FIFO must not block the open
    if msg:
        raise InputFileError(f"video.path: {msg}")
    src = FrameSource(project.resolve(v.path), v.start_s, v.end_s, v.step, v.frame_interval_s, v.capture_fps)
    lens = None
    if project.calibration.path:
        lens = load_calibration(project.resolve(project.calibration.path))
    first = read_color_frame(project.resolve(v.path), v.start_s, v.frame_interval_s, v.capture_fps)
    return Inputs(cs, src, lens, first)
