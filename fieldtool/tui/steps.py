"""The steps of the measurement (thesis figure 9.1) in order, with the parameters of each.

Each step lists the project tables it edits (for stale marking) and its ``Field``s (defaults,
units, validators and help lines). Field visibility may depend on a choice that is not a project
key (the calibration mode), kept in the session's ``ui`` dict.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fieldtool.project.model import Project
from fieldtool.project.validation import validate
from fieldtool.tui.fields import Field

# ---------------------------------------------------------------------------------------------
# small validators: value, project -> message or None


def positive(v, p):
    return None if v > 0 else f"{v:g} must be greater than 0"


def non_negative(v, p):
    return None if v >= 0 else f"{v:g} must be 0 or more"


def at_least(lo: float) -> Callable:
    return lambda v, p: None if v >= lo else f"{v:g} is too small; use {lo:g} or more"


def between(lo: float, hi: float) -> Callable:
    return lambda v, p: None if lo <= v <= hi else f"{v:g} is out of range; use {lo:g} to {hi:g}"


def increasing_pair(v, p):
    return None if v[1] > v[0] else f"the second value ({v[1]:g}) must exceed the first ({v[0]:g}): give min, max"


# ---------------------------------------------------------------------------------------------
# cross-section

_SHAPED = ("rectangular", "trapezoidal", "parabolic")


def _shape(p: Project) -> str:
    return p.cross_section.shape


CROSS_SECTION = [
    Field(
        "cross_section.shape",
        "Source",
        "",
        "choice",
        "load a surveyed 'station, elevation' file, or create the section from a shape",
        choices=(
            ("load a file", ""),
            ("rectangular", "rectangular"),
            ("trapezoidal", "trapezoidal"),
            ("parabolic", "parabolic"),
            ("free (points)", "free"),
        ),
    ),
    Field(
        "cross_section.path",
        "File",
        "",
        "path",
        "text/CSV file, one 'station, elevation' row per point in metres, left bank to right bank",
        required=lambda p: _shape(p) == "",
        show=lambda p: _shape(p) == "",
    ),
    Field(
        "cross_section.top_width_m",
        "Top width",
        "m",
        "float",
        "width between the two bank tops",
        required=lambda p: _shape(p) in _SHAPED,
        show=lambda p: _shape(p) in _SHAPED,
        check=positive,
    ),
    Field(
        "cross_section.bottom_width_m",
        "Bed width",
        "m",
        "float",
        "width of the flat bed (less than the top width)",
        required=lambda p: _shape(p) == "trapezoidal",
        show=lambda p: _shape(p) == "trapezoidal",
        check=lambda v, p: (
            None
            if 0 < v < (p.cross_section.top_width_m or float("inf"))
            else f"{v:g} m must be between 0 and the top width"
        ),
    ),
    Field(
        "cross_section.depth_m",
        "Depth",
        "m",
        "float",
        "from the bank tops down to the deepest bed point",
        required=lambda p: _shape(p) in _SHAPED,
        show=lambda p: _shape(p) in _SHAPED,
        check=positive,
    ),
    Field(
        "cross_section.left_station_m",
        "Left bank station",
        "m",
        "float",
        "reference point: station of the left bank top (left looking downstream)",
        show=lambda p: _shape(p) in _SHAPED,
    ),
    Field(
        "cross_section.bank_elevation_m",
        "Bank elevation",
        "m",
        "float",
        "reference point: elevation of the bank tops, in the datum of the water level",
        show=lambda p: _shape(p) in _SHAPED,
    ),
    Field(
        "cross_section.points",
        "Points",
        "m",
        "points",
        "free shape: 'station, elevation; station, elevation; ...' from the left bank, 2 or more",
        required=lambda p: _shape(p) == "free",
        show=lambda p: _shape(p) == "free",
        check=lambda v, p: None if len(v) >= 2 else "give at least 2 points",
    ),
]

# ---------------------------------------------------------------------------------------------
# video and stabilisation


def _end_after_start(v, p):
    return None if v > p.video.start_s else f"{v:g} s must be after the start ({p.video.start_s:g} s)"


def _stab(p: Project) -> bool:
    return p.stabilize.enabled


def _rects(v, p):
    for i, r in enumerate(v):
        if not (r[2] > r[0] and r[3] > r[1]):
            return f"region {i + 1}: give x0, y0, x1, y1 with x1 > x0 and y1 > y0"
    return None


VIDEO = [
    Field(
        "video.path",
        "Video",
        "",
        "path",
        "the clip of the river surface: a video file, an image folder, or a glob like frames/*.png",
        required=True,
    ),
    Field(
        "video.start_s",
        "Start",
        "s",
        "float",
        "first frame used, seconds from the start of the clip",
        check=non_negative,
    ),
    Field(
        "video.end_s",
        "End",
        "s",
        "float",
        "last frame used; empty = to the end of the clip",
        check=_end_after_start,
        placeholder="end of the clip",
    ),
    Field(
        "video.step",
        "Every Nth frame",
        "",
        "int",
        "use every Nth frame (1 = all; 2 halves the work)",
        check=at_least(1),
    ),
    Field(
        "video.capture_fps",
        "Filmed at",
        "fps",
        "float",
        "the rate a slow-motion or time-lapse clip was filmed at; empty = the rate the phone wrote in the file, "
        "else the file's own",
        check=positive,
        placeholder="the file's",
    ),
    Field(
        "video.auto_step",
        "Fewer frames if slow",
        "",
        "choice",
        "use every Nth frame on top of that where the water's pattern barely changes between frames (slow flow, "
        "a high frame rate); N from the clip's first frames",
        choices=(("yes", True), ("no", False)),
    ),
    Field(
        "video.frame_interval_s",
        "Frame interval",
        "s",
        "float",
        "image sequences only: time between two images; videos use their own timestamps",
        check=positive,
        placeholder="from the video timestamps",
    ),
    Field(
        "stabilize.enabled",
        "Stabilise",
        "",
        "choice",
        "register every frame on the first using fixed features on the banks (camera moved while filming)",
        choices=(("no", False), ("yes", True)),
    ),
    Field(
        "stabilize.auto",
        "Check the camera",
        "",
        "choice",
        "when not stabilised: follow the GCPs in the first frames and stabilise on them if the camera moved",
        choices=(("yes", True), ("no", False)),
        show=lambda p: not p.stabilize.enabled,
    ),
    Field(
        "stabilize.model",
        "Motion model",
        "",
        "choice",
        "homography (any camera motion) or affine (small shakes of a distant camera)",
        choices=(("homography", "homography"), ("affine", "affine")),
        show=_stab,
    ),
    Field(
        "stabilize.regions_px",
        "Stable regions",
        "px",
        "rects",
        "rectangles on the banks that do not move: 'x0, y0, x1, y1; ...' (four are recommended)",
        show=_stab,
        check=_rects,
        pickable=True,
        required=lambda p: p.stabilize.enabled and not p.stabilize.water_polygon_px,
    ),
    Field(
        "stabilize.water_polygon_px",
        "or water polygon",
        "px",
        "points",
        "instead of regions: a polygon around the water 'x, y; x, y; ...'; features outside it are used",
        show=_stab,
        pickable=True,
        check=lambda v, p: None if len(v) >= 3 else "a polygon needs at least 3 points",
    ),
    Field(
        "stabilize.max_drift_px",
        "Max drift",
        "px",
        "float",
        "steady drift of stable features above this is taken as water and dropped",
        show=_stab,
        check=positive,
        placeholder="the region side",
    ),
]

# ---------------------------------------------------------------------------------------------
# calibration

CALIBRATION_MODES = (
    ("skip (no lens correction)", "skip"),
    ("load a calibration file", "load"),
    ("calibrate from a checkerboard video", "run"),
)


def calibration_mode(p: Project) -> str:
    """The mode a project implies when it is opened."""
    c = p.calibration
    if c.checkerboard_video:
        return "run"
    return "load" if c.path else "skip"


def _corners(v, p):
    if any(c != int(c) for c in v):
        return "give whole numbers of inner corners, e.g. 9, 6"
    if min(v) < 3 or v[0] == v[1]:
        return "count the inner corners (where four squares meet); at least 3 each and different, e.g. 9, 6"
    return None


def calibration_fields(ui: dict) -> list[Field]:
    mode = lambda p: ui.get("calibration_mode", calibration_mode(p))  # noqa: E731
    return [
        Field(
            "calibration.path",
            "Calibration file",
            "",
            "path",
            "lens model written by `fieldtool calibrate` or by this step (TOML/JSON)",
            required=lambda p: mode(p) == "load",
            show=lambda p: mode(p) == "load",
        ),
        Field(
            "calibration.checkerboard_video",
            "Checkerboard video",
            "",
            "path",
            "video of a printed checkerboard filmed from many angles with the same camera and zoom",
            required=lambda p: mode(p) == "run",
            show=lambda p: mode(p) == "run",
        ),
        Field(
            "calibration.corners",
            "Inner corners",
            "",
            "floats",
            "inner corners of the board: columns, rows (where four squares meet), e.g. 9, 6",
            count=2,
            required=lambda p: mode(p) == "run",
            show=lambda p: mode(p) == "run",
            check=_corners,
        ),
        Field(
            "calibration.square_mm",
            "Square size",
            "mm",
            "float",
            "side of one square of the printed board",
            required=lambda p: mode(p) == "run",
            show=lambda p: mode(p) == "run",
            check=positive,
        ),
        Field(
            "calibration.n_frames",
            "Frames to use",
            "",
            "int",
            "the video is split in this many parts, one board view taken from each (10 to 20 is good)",
            show=lambda p: mode(p) == "run",
            check=at_least(5),
        ),
        Field(
            "calibration.path",
            "Save as",
            "",
            "text",
            "file the lens model is written to, beside the project (e.g. calibration.toml)",
            required=lambda p: mode(p) == "run",
            show=lambda p: mode(p) == "run",
        ),
    ]


# ---------------------------------------------------------------------------------------------
# orthorectification

ORTHO_METHODS = (
    ("4 GCPs and 6 distances", "distances"),
    ("GCPs with world coordinates", "world"),
    ("camera pose (6+ GCPs, lens)", "pose"),
    ("nadir: 2 GCPs and their distance", "two_points"),
    ("skip (scale from wetted width)", "none"),
)


def _om(p: Project) -> str:
    return p.ortho.method


def _world_pts(v, p):
    dims = {len(x) for x in v}
    if len(dims) > 1:
        return "give every point with the same number of coordinates (X, Y or X, Y, Z)"
    n_px = len(p.ortho.gcp_px)
    if len(v) != n_px:
        return f"{len(v)} world points for {n_px} pixel points; give one per GCP, in the same order"
    if p.ortho.method == "pose" and dims != {3}:
        return "the pose method needs X, Y, Z for every GCP"
    return None


def _gcp_shown(i: int, dist: bool = False) -> Callable[[Project], bool]:
    """GCP P(i+1) or distance L(i+1) is asked for: all four/six for 'distances', P1, P2 and L1 for 'two_points'."""
    return lambda p: _om(p) == "distances" or (_om(p) == "two_points" and i < (1 if dist else 2))


_GCP_NAMES = ("P1 (bank 1)", "P2 (bank 1)", "P3 (bank 2)", "P4 (bank 2)")
_DIST_NAMES = ("L1 = |P1P2|", "L2 = |P2P3|", "L3 = |P3P4|", "L4 = |P4P1|", "L5 = |P1P3|", "L6 = |P2P4|")

ORTHO = [
    Field(
        "ortho.method",
        "Method",
        "",
        "choice",
        "how image pixels map to metres on the water plane (thesis 7.3); skip only for a nadir view",
        choices=ORTHO_METHODS,
    ),
    *[
        Field(
            f"ortho.gcp_px[{i}]",
            name,
            "px",
            "point",
            "pixel of this ground control point 'x, y' (type it, or pick it in the viewer); "
            "P1, P2 on one bank, P3, P4 on the other, going round (fig. 7.13)",
            required=_gcp_shown(i),
            show=_gcp_shown(i),
            pickable=True,
        )
        for i, name in enumerate(_GCP_NAMES)
    ],
    *[
        Field(
            f"ortho.distances_m[{i}]",
            name,
            "m",
            "float",
            "tape-measured distance between the two GCPs",
            required=_gcp_shown(i, dist=True),
            show=_gcp_shown(i, dist=True),
            check=positive,
        )
        for i, name in enumerate(_DIST_NAMES)
    ],
    Field(
        "ortho.gcp_px",
        "GCP pixels",
        "px",
        "points",
        "GCP pixels 'x, y; x, y; ...' (4 or more; pose: 6 or more), picked or typed",
        required=lambda p: _om(p) in ("world", "pose"),
        show=lambda p: _om(p) in ("world", "pose"),
        pickable=True,
        check=lambda v, p: (
            None
            if len(v) >= (6 if p.ortho.method == "pose" else 4)
            else f"{len(v)} points; give at least {6 if p.ortho.method == 'pose' else 4}"
        ),
    ),
    Field(
        "ortho.gcp_world_m",
        "GCP world",
        "m",
        "worldpoints",
        "surveyed GCP coordinates 'X, Y; X, Y; ...' (pose: 'X, Y, Z; ...'), same order as the pixels",
        required=lambda p: _om(p) in ("world", "pose"),
        show=lambda p: _om(p) in ("world", "pose"),
        check=_world_pts,
    ),
    Field(
        "ortho.resolution_m",
        "Rectified pixel",
        "m",
        "float",
        "pixel size of the rectified image used for plots",
        check=positive,
        placeholder="automatic",
        show=lambda p: _om(p) != "none",
    ),
]

# ---------------------------------------------------------------------------------------------
# water level

LEVEL_METHODS = (
    ("set the value", "value"),
    ("from a wetted width", "width"),
    ("adapted Hellebaut (bank DEM)", "dem"),
    ("angle and height (2 images)", "angle_height"),
    ("image method (rectified frame)", "image"),
    ("water line found in the clip", "waterline"),
)


def _wm(m: str) -> Callable[[Project], bool]:
    return lambda p: p.water_level.method == m


def _two_points(v, p):
    return None if len(v) == 2 else f"{len(v)} point(s); give the left then the right water edge 'x, y; x, y'"


WATER_LEVEL = [
    Field("water_level.method", "Method", "", "choice", "how the level is found (thesis 9.2.5)", choices=LEVEL_METHODS),
    Field(
        "water_level.value_m",
        "Water level",
        "m",
        "float",
        "ELEVATION of the water surface in the cross-section's datum (not a depth)",
        required=_wm("value"),
        show=_wm("value"),
    ),
    Field(
        "water_level.uncertainty_m",
        "Uncertainty",
        "m",
        "float",
        "1-sigma of the typed level",
        show=_wm("value"),
        check=non_negative,
        placeholder="0.01 m",
    ),
    Field(
        "water_level.width_m",
        "Wetted width",
        "m",
        "float",
        "measured width, water edge to water edge",
        required=_wm("width"),
        show=_wm("width"),
        check=positive,
    ),
    Field(
        "water_level.width_uncertainty_m",
        "Width uncertainty",
        "m",
        "float",
        "1-sigma of the measured width",
        show=_wm("width"),
        check=non_negative,
        placeholder="0.02 m",
    ),
    Field(
        "water_level.dem_path",
        "DEM file",
        "",
        "path",
        "TIFF of bank elevations (m, datum of the cross-section), row 0 = y max",
        required=_wm("dem"),
        show=_wm("dem"),
    ),
    Field(
        "water_level.dem_x_m",
        "DEM x range",
        "m",
        "floats",
        "x_min, x_max of the DEM domain; x is across the river (= cross-section station)",
        count=2,
        required=_wm("dem"),
        show=_wm("dem"),
        check=increasing_pair,
    ),
    Field(
        "water_level.dem_y_m",
        "DEM y range",
        "m",
        "floats",
        "y_min, y_max of the DEM domain, along the bank",
        count=2,
        required=_wm("dem"),
        show=_wm("dem"),
        check=increasing_pair,
    ),
    Field(
        "water_level.dem_precision_mm",
        "DEM precision",
        "mm/px",
        "float",
        "DEM pixel size",
        required=_wm("dem"),
        show=_wm("dem"),
        check=positive,
    ),
    Field(
        "water_level.dem_compare_m",
        "Compare over",
        "m",
        "float",
        "length of bank, from the bank end, compared with the cross-section",
        show=_wm("dem"),
        check=positive,
        placeholder="the whole DEM",
    ),
    Field(
        "water_level.dem_section_y_m",
        "Section y in DEM",
        "m",
        "float",
        "y of the cross-section in the DEM",
        show=_wm("dem"),
        placeholder="median of all rows",
    ),
    Field(
        "water_level.divergence_station_m",
        "Divergence station",
        "m",
        "float",
        "override of the detected DEM/section divergence point (adjustment after a failed detection)",
        show=_wm("dem"),
        placeholder="detected",
    ),
    Field(
        "water_level.image1",
        "Lower image",
        "",
        "path",
        "nadir image taken at the lower height",
        required=_wm("angle_height"),
        show=_wm("angle_height"),
    ),
    Field(
        "water_level.image2",
        "Higher image",
        "",
        "path",
        "nadir image taken higher on the same vertical",
        required=_wm("angle_height"),
        show=_wm("angle_height"),
    ),
    Field(
        "water_level.dh_m",
        "Height difference",
        "m",
        "float",
        "height difference between the two images (e.g. from the drone GPS)",
        required=_wm("angle_height"),
        show=_wm("angle_height"),
        check=positive,
    ),
    Field(
        "water_level.dh_uncertainty_m",
        "dH uncertainty",
        "m",
        "float",
        "1-sigma of the height difference",
        show=_wm("angle_height"),
        check=non_negative,
    ),
    Field(
        "water_level.fov_deg",
        "Field of view",
        "deg",
        "floats",
        "FOV 'x, y, diagonal' (or 'x' for square pixels) when no calibration is loaded",
        show=_wm("angle_height"),
        placeholder="from the calibration",
        check=lambda v, p: (
            None
            if len(v) in (1, 3) and all(0 < a < 180 for a in v)
            else "give 'x' or 'x, y, diagonal' in degrees, each between 0 and 180"
        ),
    ),
    Field(
        "water_level.fov_uncertainty_deg",
        "FOV uncertainty",
        "deg",
        "float",
        "1-sigma of the field of view",
        show=_wm("angle_height"),
        check=non_negative,
    ),
    Field(
        "water_level.pixel_uncertainty_px",
        "Pick uncertainty",
        "px",
        "float",
        "1-sigma of one picked water edge",
        show=lambda p: p.water_level.method in ("angle_height", "image"),
        check=non_negative,
    ),
    Field(
        "water_level.edges1_px",
        "Edges on image 1",
        "px",
        "points",
        "left then right water edge on the lower image 'x, y; x, y'",
        required=_wm("angle_height"),
        show=_wm("angle_height"),
        check=_two_points,
        pickable=True,
    ),
    Field(
        "water_level.edges2_px",
        "Edges on image 2",
        "px",
        "points",
        "left then right water edge on the higher image 'x, y; x, y'",
        required=_wm("angle_height"),
        show=_wm("angle_height"),
        check=_two_points,
        pickable=True,
    ),
    Field(
        "water_level.edges_px",
        "Water edges",
        "px",
        "points",
        "left then right water edge on the raw frame 'x, y; x, y' (rectified with the GCP mapping)",
        required=_wm("image"),
        show=_wm("image"),
        check=_two_points,
        pickable=True,
    ),
    Field(
        "water_level.search_line_px",
        "Search line",
        "px",
        "points",
        "a line from bank to bank 'x, y; x, y' along which the water edges are found; empty = the section's "
        "points lengthened by 40 % each way",
        show=_wm("waterline"),
        check=_two_points,
        pickable=True,
    ),
    Field(
        "water_level.search_spacing_m",
        "Line spacing",
        "m",
        "float",
        "2 more search lines each side, this far apart on the water; their levels must agree (0 = one line)",
        show=_wm("waterline"),
    ),
]

# ---------------------------------------------------------------------------------------------
# ROI and masks


def _rect(v, p):
    return (
        None if v[2] > v[0] and v[3] > v[1] else "give x0, y0, x1, y1 with x1 > x0 and y1 > y0 (top-left, bottom-right)"
    )


ROI = [
    Field(
        "roi.rect_px",
        "ROI rectangle",
        "px",
        "floats",
        "where PIV runs: 'x0, y0, x1, y1' (top-left, bottom-right corner); empty = whole frame",
        count=4,
        check=_rect,
        pickable=True,
        placeholder="whole frame",
    ),
    Field(
        "roi.masks_px",
        "Masks",
        "px",
        "polygons",
        "areas whose vectors are invalid: 'x, y; x, y; x, y' per polygon, polygons separated by |",
        pickable=True,
        placeholder="none",
    ),
]

# ---------------------------------------------------------------------------------------------
# PIV


def _overlap(v, p):
    return (
        None
        if 0 <= v < p.piv.window_px
        else f"{v} px must be 0 or more and less than the window ({p.piv.window_px} px)"
    )


def _search(v, p):
    return None if v >= p.piv.window_px else f"{v} px must be at least the window ({p.piv.window_px} px)"


PIV = [
    Field(
        "piv.window_px",
        "Window",
        "px",
        "int",
        "interrogation window side; a particle should move less than a quarter of it between frames",
        check=at_least(8),
    ),
    Field(
        "piv.overlap_px",
        "Overlap",
        "px",
        "int",
        "overlap between neighbouring windows (half the window is usual)",
        check=_overlap,
    ),
    Field(
        "piv.snr_min",
        "Min SNR",
        "",
        "float",
        "signal-to-noise ratio (peak to second peak) below which a vector is invalid",
        check=at_least(1.0),
    ),
    Field(
        "piv.search_px",
        "Search area",
        "px",
        "int",
        "search area side in the first pass",
        check=_search,
        placeholder="= window",
    ),
    Field(
        "piv.passes",
        "Passes",
        "",
        "int",
        "multi-pass with window deformation; the window halves each pass",
        check=between(1, 4),
    ),
    Field(
        "piv.averaging",
        "Averaging",
        "",
        "choice",
        "ensemble: average correlation planes (robust on sparse seeding); mean or median of the pair fields",
        choices=(("ensemble", "ensemble"), ("mean", "mean"), ("median", "median")),
    ),
    Field(
        "piv.engine",
        "Engine",
        "",
        "choice",
        "fieldtool's FFT correlation, or OpenPIV's",
        choices=(("fieldtool", "fieldtool"), ("openpiv", "openpiv")),
    ),
    Field(
        "piv.max_velocity_ms",
        "Max velocity",
        "m/s",
        "float",
        "faster vectors are invalid",
        check=positive,
        placeholder="no limit",
    ),
    Field("piv.median_threshold", "Median test", "", "float", "normalised local median test threshold", check=positive),
    Field(
        "piv.std_threshold",
        "Std test",
        "sigma",
        "float",
        "global test: vectors beyond n sigma are invalid",
        check=positive,
    ),
    Field(
        "piv.min_valid_fraction",
        "Min valid fraction",
        "",
        "float",
        "a node valid in fewer pairs than this fraction is dropped from the average",
        check=between(0, 1),
    ),
]

# ---------------------------------------------------------------------------------------------
# section of interest


SECTION = [
    Field(
        "section.points_px[0]",
        "P1 left water edge",
        "px",
        "point",
        "left water edge (looking downstream) on the raw frame 'x, y'",
        required=True,
        pickable=True,
    ),
    Field(
        "section.points_px[1]",
        "P2 right water edge",
        "px",
        "point",
        "right water edge on the raw frame 'x, y'",
        required=True,
        pickable=True,
    ),
    Field("section.n_sub", "Subsections", "", "int", "number of subsections across the section", check=at_least(1)),
    Field(
        "section.station_offset_m",
        "Station of P1",
        "m",
        "float",
        "cross-section station of P1",
        placeholder="the left water edge",
    ),
    Field(
        "section.alpha",
        "Velocity index",
        "",
        "float",
        "surface to depth-averaged velocity (alpha)",
        check=between(0.3, 1.2),
        placeholder="0.8; 0.9 if mean depth >= 2 m",
    ),
]


# ---------------------------------------------------------------------------------------------
# the steps


@dataclass(frozen=True)
class Step:
    id: str
    title: str
    tables: tuple[str, ...]  # project tables this step edits


STEPS: tuple[Step, ...] = (
    Step("cross_section", "Cross-section", ("cross_section",)),
    Step("video", "Video", ("video", "stabilize")),
    Step("calibration", "Calibration", ("calibration",)),
    Step("ortho", "Orthorectification", ("ortho",)),
    Step("water_level", "Water level", ("water_level",)),
    Step("roi", "ROI and masks", ("roi",)),
    Step("filters", "Filters", ("filters",)),
    Step("piv", "PIV", ("piv",)),
    Step("section", "Section", ("section",)),
    Step("results", "Discharge", ()),
)
STEP_IDS = tuple(s.id for s in STEPS)
STEP_BY_ID = {s.id: s for s in STEPS}

# tables the PIV field depends on (the rest only change the discharge)
PIV_TABLES = ("video", "calibration", "stabilize", "roi", "filters", "piv")


# the measurement's own description (printed on the report), on the discharge step below the result
MEASUREMENT = [
    Field("name", "Name", "", "text", "a name for this measurement (station, date); the report's title"),
    Field("site", "Site", "", "text", "site this measurement belongs to (see `fieldtool site`); on the report"),
    Field("station", "Station", "", "text", "gauging station name or code; on the report"),
    Field("operator", "Operator", "", "text", "who made the measurement; on the report"),
]


def fields_for(step: str, ui: dict) -> list[Field]:
    """The Fields of a step."""
    return {
        "cross_section": CROSS_SECTION,
        "video": VIDEO,
        "calibration": calibration_fields(ui),
        "ortho": ORTHO,
        "water_level": WATER_LEVEL,
        "roi": ROI,
        "piv": PIV,
        "section": SECTION,
    }.get(step, [])


def step_problems(step: str, project: Project, *, files: bool = True):
    """Problems of the validation layer (``fieldtool.project.validation``) on the tables a step edits."""
    tables = STEP_BY_ID[step].tables if step in STEP_BY_ID else ()
    return [p for p in validate(project, files=files) if p.key.split(".")[0].split("[")[0] in tables]
