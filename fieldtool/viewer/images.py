"""The images the viewer shows, each with the mapping between its pixels and raw-frame pixels.

Picks are stored in raw-frame pixels (see fieldtool.project.model). A :class:`Display` knows how to map
raw-frame points onto itself (``to_display``) and back (``from_display``), so the same picks can be
drawn and clicked on the first frame, on the undistorted frame and on the orthorectified map.

Kinds: ``frame`` (first frame of the range, as recorded), ``working`` (lens distortion removed;
stabilisation registers on this frame, so it is also the stabilised frame 0), ``ortho`` (map of
the water plane), ``image1`` / ``image2`` (the two nadir images of the angle-and-height method),
``dem_plot`` (DEM vs surveyed bed, Hellebaut method; its ``axes`` map a click to a station),
``filtered`` (the TUI's filter preview, ``out/filter_preview.png``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from fieldtool.errors import FieldToolError, InputFileError, ParameterError
from fieldtool.processing import water_level as wl
from fieldtool.processing.calibration import load_calibration
from fieldtool.processing.frames import read_color_frame
from fieldtool.project.model import Project
from fieldtool.run.geometry import build_mapping, compute_level
from fieldtool.run.inputs import load_cross_section, load_inputs
from fieldtool.viewer.mapping import PlotAxes
from fieldtool.viewer.plot_image import Curve, render_plot

KINDS = {
    "frame": "First frame",
    "working": "Undistorted / stabilised frame",
    "ortho": "Orthorectified map",
    "image1": "Angle-and-height image 1",
    "image2": "Angle-and-height image 2",
    "dem_plot": "DEM vs bed (Hellebaut)",
    "filtered": "Filter preview (TUI)",
}
FRAME_LIKE = ("frame", "working", "ortho")  # displays on which raw-frame picks are made


def _identity(p) -> np.ndarray:
    return np.asarray(p, float).reshape(-1, 2)


@dataclass
class Display:
    """An RGB image and how its pixels relate to raw-frame pixels."""

    kind: str
    rgb: np.ndarray  # (H, W, 3) uint8
    to_display: Callable[[np.ndarray], np.ndarray] = _identity  # raw (N, 2) -> display (N, 2)
    from_display: Callable[[np.ndarray], np.ndarray] = _identity  # display (N, 2) -> raw (N, 2)
    axes: PlotAxes | None = None  # dem_plot: data axes
    note: str = ""

    @property
    def pick_image(self) -> str:
        """The image kind picks made here belong to (``frame`` for the frame-like displays)."""
        return "frame" if self.kind in FRAME_LIKE else self.kind


def _rgb(bgr: np.ndarray) -> np.ndarray:
    if bgr.ndim == 2:
        return cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _first_frame(project: Project) -> np.ndarray:
    v = project.video
    if not v.path:
        raise ParameterError("video.path: no video given; set the clip to analyse")
    return read_color_frame(project.resolve(v.path), v.start_s, v.frame_interval_s, v.capture_fps)


def lens_of(project: Project):
    """The lens model of the project, or None without calibration.path."""
    if not project.calibration.path:
        return None

    return load_calibration(project.resolve(project.calibration.path))


def load_display(project: Project, kind: str) -> Display:
    """Build the display of ``kind`` for ``project``. Raises FieldToolError with the reason when
    the project does not (yet) have what the image needs."""
    if kind == "frame":
        return Display("frame", _rgb(_first_frame(project)))
    if kind == "working":
        lens = lens_of(project)
        img = _first_frame(project)
        if lens is None:
            return Display("working", _rgb(img), note="no lens model (calibration.path): same as the first frame")
        return Display("working", _rgb(lens.undistort(img)), lens.undistort_points, lens.distort_points)
    if kind == "ortho":
        return _ortho(project)
    if kind in ("image1", "image2"):
        rel = getattr(project.water_level, kind)
        if not rel:
            raise ParameterError(f"water_level.{kind}: no image given for the angle-and-height method")
        path = project.resolve(rel)
        photo = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if photo is None:
            raise InputFileError(f"{path}: cannot be read as an image (water_level.{kind})")
        return Display(kind, _rgb(photo))
    if kind == "dem_plot":
        return _dem_plot(project)
    if kind == "filtered":  # written by the TUI's filter preview: the working frame, filtered
        path = project.root / "out" / "filter_preview.png"
        preview = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if preview is None:
            raise InputFileError(f"{path}: no filter preview yet; press ctrl+r on the filters step of the TUI")
        lens = lens_of(project)
        if lens is None:
            return Display("filtered", _rgb(preview))
        return Display("filtered", _rgb(preview), lens.undistort_points, lens.distort_points)
    raise ParameterError(f"unknown image {kind!r}; one of {', '.join(KINDS)}")


def _ortho(project: Project) -> Display:
    inputs = load_inputs(project)
    level = None
    if project.ortho.method in ("none", "pose"):
        level = compute_level(project, inputs, None).level_m
    mapping = build_mapping(project, inputs, level)
    work = inputs.lens.undistort(inputs.first_color) if inputs.lens is not None else inputs.first_color
    rect, A = mapping.rectified_image(work, resolution_m=project.ortho.resolution_m)
    A_inv = np.linalg.inv(A)
    lens = inputs.lens

    def to_display(raw):
        world = mapping.image_to_world(inputs.to_working(raw))
        q = np.c_[world, np.ones(len(world))] @ A.T
        return q[:, :2] / q[:, 2:]

    def from_display(pts):
        p = np.asarray(pts, float).reshape(-1, 2)
        q = np.c_[p, np.ones(len(p))] @ A_inv.T
        work_px = mapping.world_to_image(q[:, :2] / q[:, 2:])
        return lens.distort_points(work_px) if lens is not None else work_px

    r = 1.0 / A[0, 0]
    return Display(
        "ortho",
        _rgb(rect),
        to_display,
        from_display,
        note=f"map of the water plane, {r * 1000:.1f} mm/pixel, north-up in the GCP frame",
    )


def _dem_plot(project: Project) -> Display:
    cfg = project.water_level
    if not cfg.dem_path:
        raise ParameterError("water_level.dem_path: no DEM given; the DEM plot needs the bank's DEM (TIFF)")

    cs = load_cross_section(project)
    dem = wl.read_dem(project.resolve(cfg.dem_path))
    st, prof = wl.dem_profile(
        dem, cfg.dem_x_m, cfg.dem_y_m, cfg.dem_precision_mm, cs, getattr(cfg, "dem_section_y_m", None)
    )
    curves = [
        Curve("surveyed bed", np.asarray(cs.station), np.asarray(cs.elevation), (40, 40, 40)),
        Curve("DEM", st, prof, (30, 110, 220)),
    ]
    vlines = []
    note = ""
    try:
        bed = np.interp(st, cs.station, cs.elevation)
        auto = wl.hellebaut_divergence(st, prof, bed, cfg.dem_compare_m)
        vlines.append((float(auto["station_m"][auto["index"]]), (0, 150, 0), "automatic"))
    except FieldToolError as e:
        note = f"no automatic divergence point: {e}"
    img, axes = render_plot(
        curves,
        title="DEM vs surveyed bed: click where they diverge",
        xlabel="station (m, left bank -> right bank)",
        ylabel="elevation (m)",
        vlines=vlines,
    )
    return Display("dem_plot", img, axes=axes, note=note)


def load_field(path: Path | str) -> dict[str, np.ndarray] | None:
    """Mean velocity field of a run (``mean_field.npz``): node positions x, y and velocities u, v
    (px/s) in working-image pixels (undistorted when a lens model is used), and ``valid``.

    Returns None when the file does not exist (no run yet)."""
    path = Path(path)
    if not path.is_file():
        return None
    with np.load(path) as z:
        x, y, u, v = (np.asarray(z[k], float) for k in ("x_px", "y_px", "u_px_s", "v_px_s"))
        valid = np.asarray(z["valid"], bool) if "valid" in z else np.isfinite(u) & np.isfinite(v)
    return {"x": x, "y": y, "u": u, "v": v, "valid": valid & np.isfinite(u) & np.isfinite(v)}
