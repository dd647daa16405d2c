"""The Project: every input, parameter and pick of one measurement, read and written as TOML.

Each TOML table maps one-to-one to a dataclass below, and each key to a field of the same name.
Units are in the key names (``_m`` metres, ``_s`` seconds, ``_px`` pixels, ``_ms`` m/s).
Relative paths are relative to the folder of the project file. Pixel coordinates are image
coordinates of the raw video frame: x right, y down, origin at the centre of the top-left pixel.

A field set to ``None`` is "not given" and is left out of the file (TOML has no null).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w
import tomlkit

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.project.keyspec import key
from fieldtool.project.textfile import read_text

try:  # POSIX only: the project folder's save lock (_DirLock); Windows has none
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

Point = list[float]


@dataclass
class VideoCfg:
    """[video] the clip to analyse."""

    path: str = key("", path="video")  # video file (any format ffmpeg reads), image folder, or glob like "frames/*.png"
    start_s: float = key(0.0, unit="s", ge=0.0, le=1e6)  # first frame used, seconds from the start of the clip
    end_s: float | None = key(None, unit="s", gt=0.0, le=1e6)  # last frame used (s); None = to the end
    step: int = key(1, ge=1, le=10000)  # use every step-th frame (1 = all)
    frame_interval_s: float | None = key(None, unit="s", gt=0.0, le=86400.0)  # image sequences only: time between two images (s)
    capture_fps: float | None = key(None, unit="1/s", gt=0.0, le=100000.0)  # videos only: the rate the clip was filmed at (slow motion, time-lapse); None = the file's com.android.capture.fps tag, else its own rate
    auto_step: bool = key(True)  # use every n-th frame where the water's pattern changes little from frame to frame (slow flow, high frame rates); n from the clip


@dataclass
class CrossSectionCfg:
    """[cross_section] the surveyed bed, station from the left bank to the right bank."""

    path: str = key("", path="file")  # text/CSV file of "station, elevation" rows in metres; used when shape = ""
    shape: str = key("", choices=("", "rectangular", "trapezoidal", "parabolic", "free"))  # "" (use path) | rectangular | trapezoidal | parabolic | free
    top_width_m: float | None = key(None, unit="m", gt=0.0, le=1e5)  # width at the top of the banks (rectangular, trapezoidal, parabolic)
    bottom_width_m: float | None = key(None, unit="m", ge=0.0, le=1e5)  # trapezoidal: width of the flat bed
    depth_m: float | None = key(None, unit="m", gt=0.0, le=1e4)  # bank top to deepest bed point
    left_station_m: float = key(0.0, unit="m", ge=-1e6, le=1e6)  # reference point: station of the left bank top
    bank_elevation_m: float = key(0.0, unit="m", ge=-1e5, le=1e5)  # reference point: elevation of the bank tops
    points: list[Point] = key(factory=list, unit="m", dim=2, ge=-1e6, le=1e6, max_items=100000)  # free shape: [[station_m, elevation_m], ...]


@dataclass
class CalibrationCfg:
    """[calibration] lens model from a checkerboard video (see `fieldtool calibrate`)."""

    path: str = key("", path="file")  # calibration file written by `fieldtool calibrate`; "" = no lens correction
    checkerboard_video: str = key("", path="video")  # checkerboard video, to run the calibration from the project
    corners: list[int] = key(factory=lambda: [9, 6], counts=(2,), ge=2, le=100)  # inner corners (columns, rows)
    square_mm: float | None = key(None, unit="mm", gt=0.0, le=10000.0)  # side of one square (mm)
    n_frames: int = key(20, ge=1, le=1000)  # the video is split in n parts; first frame with a board in each


@dataclass
class StabilizeCfg:
    """[stabilize] register every frame on the first using stable features outside the water."""

    enabled: bool = False
    auto: bool = key(True)  # enabled = false: follow the GCPs in the first frames, stabilise on them if the camera moved
    regions_px: list[list[float]] = key(factory=list, unit="px", dim=4, ge=-1e5, le=1e5, max_items=100)  # rectangles [x0, y0, x1, y1]
    water_polygon_px: list[Point] = key(factory=list, unit="px", dim=2, ge=-1e5, le=1e5, max_items=10000)  # or: polygon around the water to exclude
    model: str = key("homography", choices=("homography", "affine"))  # homography | affine
    max_drift_px: float | None = key(None, unit="px", gt=0.0, le=1e4)  # steady drift (px) past which the picture is checked for water; None = half a region side


@dataclass
class OrthoCfg:
    """[ortho] image -> water-plane mapping from ground control points (GCPs).

    GCP order (thesis figure 7.13): P1, P2 on one bank, P3, P4 on the other, going round the
    quadrilateral. distances_m = [L1, L2, L3, L4, L5, L6] = |P1P2|, |P2P3|, |P3P4|, |P4P1|,
    |P1P3|, |P2P4|.
    """

    method: str = key("distances", choices=("distances", "world", "pose", "two_points", "none"))  # distances | world | pose | two_points (nadir, P1 P2 + |P1P2|) | none
    gcp_px: list[Point] = key(factory=list, unit="px", dim=2, ge=-1e5, le=1e5, max_items=1000)  # [[x, y], ...] pixels, P1..P4 (pose: 6+)
    distances_m: list[float] = key(factory=list, unit="m", gt=0.0, le=1e5, counts=(0, 1, 6))  # L1..L6 (method = distances); [|P1P2|] (method = two_points)
    gcp_world_m: list[list[float]] = key(factory=list, unit="m", dim=(2, 3), ge=-1e8, le=1e8, max_items=1000)  # [[X, Y], ...] or [[X, Y, Z], ...] (pose)
    fit_lens: bool = key(False)  # pose without calibration.path: fit focal length and k1 from 8+ GCPs (X, Y, Z)
    resolution_m: float | None = key(None, unit="m", gt=0.0, le=100.0)  # pixel size of the rectified image (m); None = automatic
    max_residual_m: float = key(0.10, unit="m", gt=0.0, le=1e4)  # largest GCP distance / world-point residual accepted (m); above it the run stops naming the suspect
    accept_residual: bool = key(False)  # go on despite a residual above max_residual_m (the grade becomes doubtful)
    crs_epsg: int | None = key(None, ge=1024, le=999999)  # EPSG code of gcp_world_m (method world/pose), e.g. 28992; writes rectified.tif


@dataclass
class WaterLevelCfg:
    """[water_level] elevation of the water surface, in the cross-section's datum (thesis ch. 5)."""

    method: str = key("value", choices=("value", "width", "dem", "angle_height", "image", "waterline"))  # value | width | dem | angle_height | image | waterline (edges found in the clip)
    value_m: float | None = key(None, unit="m", ge=-1e5, le=1e5)  # method = value: typed level (m, datum of the cross-section, not a depth)
    uncertainty_m: float | None = key(None, unit="m", ge=0.0, le=100.0)  # method = value: 1-sigma of the typed level (m); None = 0.01 m
    width_m: float | None = key(None, unit="m", gt=0.0, le=1e5)  # method = width: measured wetted width, water edge to water edge (m)
    width_uncertainty_m: float | None = key(None, unit="m", ge=0.0, le=1e4)  # method = width: 1-sigma of that width (m); None = 0.02 m
    # adapted Hellebaut (DEM of one bank, x across the river = cross-section station, y along the shore)
    dem_path: str = key("", path="file")  # raster of elevations, any GDAL format (GeoTIFF, .asc, ...; m, datum of the cross-section); row 0 = y_max
    dem_x_m: list[float] = key(factory=list, unit="m", counts=(0, 2), ge=-1e7, le=1e7)  # [x_min, x_max] of the DEM domain (m, = station)
    dem_y_m: list[float] = key(factory=list, unit="m", counts=(0, 2), ge=-1e7, le=1e7)  # [y_min, y_max] of the DEM domain (m)
    dem_precision_mm: float | None = key(None, unit="mm", gt=0.0, le=1e6)  # DEM pixel size (mm/pixel); checked against domain / size
    dem_compare_m: float | None = key(None, unit="m", gt=0.0, le=1e6)  # length of bank, from the bank end, compared with the section (m); None = all
    dem_section_y_m: float | None = key(None, unit="m", ge=-1e7, le=1e7)  # y of the cross-section in the DEM (m); None = median of all rows
    divergence_station_m: float | None = key(None, unit="m", ge=-1e6, le=1e6)  # user override of the detected divergence point (station, m)
    # angle and height (two nadir images on one vertical; their heights are solved, not given)
    image1: str = key("", path="file")  # image taken at the lower height H
    image2: str = key("", path="file")  # image taken at the higher height H + dh_m
    dh_m: float | None = key(None, unit="m", gt=0.0, le=1e4)  # height difference between the two images (m), e.g. from the drone GPS
    dh_uncertainty_m: float = key(0.05, unit="m", ge=0.0, le=1e3)  # 1-sigma of dh_m (m)
    pixel_uncertainty_px: float = key(2.0, unit="px", ge=0.0, le=1000.0)  # 1-sigma of one picked water edge (px); also for method = image
    fov_deg: list[float] = key(factory=list, unit="deg", gt=0.0, lt=180.0, counts=(0, 1, 3))  # [x, y, diagonal] FOV (deg) if no calibration; [x] = square pixels
    fov_uncertainty_deg: float = key(0.5, unit="deg", ge=0.0, le=90.0)  # 1-sigma of the FOV (deg)
    edges1_px: list[Point] = key(factory=list, unit="px", dim=2, counts=(0, 2), ge=-1e5, le=1e5)  # left and right water edges on image 1 [[x, y], [x, y]]
    edges2_px: list[Point] = key(factory=list, unit="px", dim=2, counts=(0, 2), ge=-1e5, le=1e5)  # left and right water edges on image 2
    # image method: left and right water edges on the raw frame, mapped with the ortho mapping
    edges_px: list[Point] = key(factory=list, unit="px", dim=2, counts=(0, 2), ge=-1e5, le=1e5)
    # waterline: a line from bank to bank on the raw frame along which the water edges are found; [] = the
    # section's points lengthened by 40 % each way
    search_line_px: list[Point] = key(factory=list, unit="px", dim=2, counts=(0, 2), ge=-1e5, le=1e5)
    search_spacing_m: float = key(0.4, unit="m", ge=0.0, le=100.0)  # waterline: 2 more lines each side of the search line, this far apart on the water (m); their levels must agree; 0 = one line


@dataclass
class RoiCfg:
    """[roi] where PIV runs, and what it must ignore."""

    rect_px: list[float] = key(factory=list, unit="px", counts=(0, 4), ge=-1e5, le=1e5)  # [x0, y0, x1, y1]; [] = whole frame
    masks_px: list[list[Point]] = key(factory=list, unit="px", dim=2, ge=-1e5, le=1e5, max_items=1000)  # polygons whose vectors are invalid


@dataclass
class PivCfg:
    """[piv] correlation and validation parameters."""

    engine: str = key("fieldtool", choices=("fieldtool", "openpiv"))  # fieldtool | openpiv
    window_px: int = key(32, unit="px", ge=8, le=512)  # interrogation window side (px)
    overlap_px: int = key(16, unit="px", ge=0, le=511)  # overlap between windows (px)
    search_px: int | None = key(None, unit="px", ge=8, le=1024)  # search area side (px); None = window_px
    passes: int = key(2, ge=1, le=5)  # multi-pass with window deformation: first window = window_px * 2**(passes-1); 2 removes the loss-of-pairs bias
    snr_min: float = key(1.3, ge=1.0, le=100.0)  # minimum ratio of the correlation peak to the highest other local maximum
    averaging: str = key("ensemble", choices=("ensemble", "mean", "median"))  # ensemble | mean | median
    max_velocity_ms: float | None = key(None, unit="m/s", gt=0.0, le=100.0)  # vectors faster than this are invalid (m/s)
    median_threshold: float = key(2.0, gt=0.0, le=100.0)  # normalised local median test threshold
    std_threshold: float = key(4.0, gt=0.0, le=100.0)  # global standard-deviation test (n sigma)
    min_valid_fraction: float = key(0.3, ge=0.0, le=1.0)  # mean/median: a node valid in fewer pairs than this is dropped
    remove_stationary: bool = key(True)  # standardise each pixel over ~1 s before PIV: glints and patterns fixed in the image go
    remove_zero_peak: bool = key(True)  # ensemble: a peak at zero displacement where the node moves is not the flow (glints)
    frame_gap: int | None = key(None, ge=1, le=100)  # frames between the two images of a pair; None = chosen from a first look at the clip
    reject_upstream: bool = key(True)  # subsections going upstream while the section goes downstream: rejected, filled, reported
    region: str = key("section", choices=("section", "roi", "full"))  # section (a band around the section(s), within the ROI) | roi | full (whole frame)
    all_pairs: bool = key(False)  # true: correlate every pair; false: add pairs until the discharge has converged
    converge_rel_ci: float = key(0.005, gt=0.0, le=1.0)  # stop when the 95 % interval of the 10 %-trimmed mean per-pair Q is within +- this fraction
    min_pairs: int = key(30, ge=2, le=100000)  # fewest pairs before the convergence test


@dataclass
class SectionCfg:
    """[section] section of interest and discharge parameters."""

    points_px: list[Point] = key(factory=list, unit="px", dim=2, counts=(0, 2), ge=-1e5, le=1e5)  # 2 image points: left then right water edge
    n_sub: int = key(15, ge=1, le=1000)  # number of subsections
    station_offset_m: float | None = key(None, unit="m", ge=-1e6, le=1e6)  # station of the first point; None = left water edge
    alpha: float | None = key(None, gt=0.0, le=1.5)  # velocity index; None = 0.8 if mean depth < 2 m else 0.9
    min_length_fraction: float = key(0.5, ge=0.0, le=1.0)  # a section shorter than this fraction of the wetted width is refused
    edge_tolerance_m: float | None = key(None, unit="m", ge=0.0, le=1e4)  # largest distance of the section's ends from the water edges (m); None = 10 % of the wetted width, at least 0.3 m
    velocity_source: str = key("auto", choices=("auto", "piv", "stiv", "combined"))  # auto (combined where PIV and STIV agree, else PIV) | piv | stiv | combined (confidence-weighted per subsection); see [stiv]


@dataclass
class StivCfg:
    """[stiv] space-time image velocimetry on search lines across the section: a second estimator."""

    enabled: bool = key(True)  # sample the lines during the PIV's frame stream and report STIV beside PIV
    method: str = key("fft", choices=("fft", "tensor"))  # fft (2-D autocorrelation of the space-time image) | tensor (structure tensor)
    line_length_m: float = key(3.0, unit="m", gt=0.0, le=1e3)  # length of each search line along the flow, centred on the section (m)
    lines_per_sub: int = key(2, ge=1, le=20)  # search lines per subsection
    angles_deg: list[float] = key(factory=lambda: [-30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0], unit="deg", ge=-80.0, le=80.0, counts=tuple(range(1, 37)))  # line turns from the section normal (deg), all sampled; the one nearest the PIV flow direction is analysed
    min_confidence: float = key(0.1, ge=0.0, le=1.0)  # lines below this confidence (0..1) are not used


@dataclass
class QualityCfg:
    """[quality] limits of the measurement's grade (good / doubtful / unusable); see the README's quality section."""

    measured_width_doubtful: float = key(0.8, ge=0.0, le=1.0)  # fraction of the section width with a measured (not filled) velocity below which Q is doubtful
    measured_width_unusable: float = key(0.4, ge=0.0, le=1.0)  # ... below which Q is unusable
    valid_fraction_doubtful: float = key(0.5, ge=0.0, le=1.0)  # mean fraction of frame pairs with a valid vector along the section: doubtful below
    valid_fraction_unusable: float = key(0.15, ge=0.0, le=1.0)  # ... unusable below
    stalled_ratio: float = key(0.3, ge=0.0, le=1.0)  # a subsection slower than this times the fastest on each side of it (moving downstream) is stalled
    stalled_width_unusable: float = key(0.3, ge=0.0, le=1.0)  # stalled share of the width above which Q is unusable (any stalled: doubtful)
    deficit_ratio: float = key(0.8, ge=0.0, le=1.0)  # a subsection below this times the velocity its depth suggests (v ~ depth^(2/3)) is in deficit
    deficit_q_doubtful: float = key(0.03, ge=0.0, le=10.0)  # discharge the subsections in deficit may miss (up to their depth's velocity) / Q: doubtful above
    deficit_q_unusable: float = key(0.5, ge=0.0, le=10.0)  # ... unusable above
    displacement_doubtful: float = key(0.25, gt=0.0, le=1.0)  # 95th-percentile displacement along the section / first-pass search side: doubtful above
    displacement_unusable: float = key(0.45, gt=0.0, le=1.0)  # ... unusable above
    peak_min: float = key(0.15, ge=0.0, le=1.0)  # median correlation peak (coefficient) along the section: doubtful below
    pair_spread_max: float = key(0.35, ge=0.0, le=100.0)  # half the 16-84 % spread of the per-pair discharges / Q: doubtful above
    angle_doubtful_deg: float = key(20.0, unit="deg", ge=0.0, le=180.0)  # mean flow direction off the section normal (deg): doubtful above
    angle_unusable_deg: float = key(60.0, unit="deg", ge=0.0, le=180.0)  # ... unusable above
    identical_frames_doubtful: float = key(0.05, ge=0.0, le=1.0)  # fraction of identical consecutive frames: doubtful above
    identical_frames_unusable: float = key(0.5, ge=0.0, le=1.0)  # ... unusable above
    min_motion_px: float = key(0.1, unit="px", ge=0.0, le=1e3)  # median displacement along the section (px/frame) below which nothing moved: unusable
    max_surface_speed_ms: float = key(15.0, unit="m/s", gt=0.0, le=1e3)  # surface speed along the section (m/s) above which Q is unusable
    relative_u95_doubtful: float = key(0.2, ge=0.0, le=100.0)  # half-width of the 95 % interval / Q above which Q is doubtful
    sections_cv_doubtful: float = key(0.1, ge=0.0, le=100.0)  # several sections: coefficient of variation of their discharges above which Q is doubtful


@dataclass
class UncertaintyCfg:
    """[uncertainty] 1-sigma of the inputs the Monte Carlo interval of Q propagates (0 switches a source off)."""

    gcp_px_sigma_px: float = key(1.0, unit="px", ge=0.0, le=1e3)  # each picked GCP pixel coordinate (px)
    gcp_distance_sigma_m: float = key(0.01, unit="m", ge=0.0, le=1e3)  # each taped distance L1..L6, or each GCP world coordinate (m)
    bed_sigma_m: float = key(0.02, unit="m", ge=0.0, le=1e3)  # each surveyed bed elevation of the cross-section (m)
    alpha_sigma: float | None = key(None, ge=0.0, le=1.0)  # velocity index; None = 0.05 for the rule of thumb, 0.03 for a typed section.alpha
    filled_rel_sigma: float = key(0.25, ge=0.0, le=10.0)  # velocity of a subsection filled from a neighbour (relative)
    piv_rel_sigma: float = key(0.01, ge=0.0, le=1.0)  # systematic error of the PIV surface velocity (relative): sub-pixel bias, window averaging
    underread_doubtful: float = key(0.5, ge=0.0, le=0.95)  # quality doubts the velocities (stalled, deficit, valid fraction, spread, peaks, displacement, STIV faster and disagreeing): they may be under-read by up to this fraction (a prior: STIV's disagreement with PIV narrows it where measured; it also caps the over-read STIV supports where it reads slower)
    underread_unusable: float = key(0.8, ge=0.0, le=0.95)  # ... and when those reasons make it unusable
    n_draws: int = key(400, ge=20, le=100000)  # Monte Carlo draws of Q (each source's share: a quarter of that each)
    seed: int = key(0, ge=0, le=2**31)  # seed of the draws (same inputs, same interval)


@dataclass
class RerunCfg:
    """[rerun] stream to a supervisor. Off by default; rerun's servers listen on all interfaces."""

    mode: str = key("off", choices=("off", "save", "connect", "serve"))  # off | save | connect | serve
    path: str = key("run.rrd", path="out")  # mode = save: file written in the output folder
    url: str = key("", max_items=2000)  # mode = connect: rerun+http://HOST:PORT/proxy


@dataclass
class ViewerCfg:
    """[viewer] the picking web page (`fieldtool view`, the TUI's viewer)."""

    port: int = key(0, ge=0, le=65535)  # TCP port on 127.0.0.1; 0 = chosen free at the first launch, then remembered


@dataclass
class OverlayCfg:
    """[overlay] overlay.mp4: the analysed clip with the vectors, the section and Q drawn on it, made while the
    run streams the frames (see fieldtool/run/overlay_stage.py)."""

    enabled: bool = key(False)  # write overlay.mp4 into the output folder (also: fieldtool run --overlay)
    view: str = key("camera", choices=("camera", "rectified"))  # camera (frames as the run saw them: lens and stabilisation applied) | rectified (north-up map of the water plane)
    width_px: int = key(960, ge=0, le=7680)  # frame width of the video (px, rounded down to even, never above the clip's); 0 = the clip's own width
    fps: float | None = key(None, unit="1/s", gt=0.0, le=240.0)  # frames per second of the video (frames are dropped, never repeated); None = the clip's rate after video.step
    colormap: str = key("viridis", choices=("viridis", "cividis"))  # perceptual colour map of the velocities: viridis | cividis
    card_s: float = key(2.0, unit="s", ge=0.0, le=30.0)  # closing card with the final Q, its 95 % interval and the grade (s); 0 = none


@dataclass
class Project:
    """One measurement. ``root`` is the folder relative paths are resolved from (not saved)."""

    name: str = key("measurement", max_items=200)  # a name for this measurement (station, date)
    site: str = key("", max_items=200)  # site this measurement belongs to ("" = none); see `fieldtool site`
    operator: str = key("", max_items=200)  # who made the measurement (printed on the report)
    station: str = key("", max_items=200)  # gauging station name or code (printed on the report)
    step: str = key("cross_section", max_items=64)  # last TUI step visited
    video: VideoCfg = field(default_factory=VideoCfg)
    cross_section: CrossSectionCfg = field(default_factory=CrossSectionCfg)
    calibration: CalibrationCfg = field(default_factory=CalibrationCfg)
    stabilize: StabilizeCfg = field(default_factory=StabilizeCfg)
    ortho: OrthoCfg = field(default_factory=OrthoCfg)
    water_level: WaterLevelCfg = field(default_factory=WaterLevelCfg)
    roi: RoiCfg = field(default_factory=RoiCfg)
    filters: list[dict[str, Any]] = key(factory=list, max_items=32)  # ordered stack: [{name = "clahe", ...}]
    piv: PivCfg = field(default_factory=PivCfg)
    section: SectionCfg = field(default_factory=SectionCfg)
    stiv: StivCfg = field(default_factory=StivCfg)
    # more sections of interest on the same field: [{name = "upstream", points_px = [[x, y], [x, y]],
    # cross_section = "upstream.csv"}, ...]; see fieldtool/project/sections.py
    sections: list[dict[str, Any]] = key(factory=list, max_items=20)
    rerun: RerunCfg = field(default_factory=RerunCfg)
    quality: QualityCfg = field(default_factory=QualityCfg)
    uncertainty: UncertaintyCfg = field(default_factory=UncertaintyCfg)
    viewer: ViewerCfg = field(default_factory=ViewerCfg)
    overlay: OverlayCfg = field(default_factory=OverlayCfg)
    root: Path = field(default=Path("."), metadata={"saved": False})

    def resolve(self, rel: str) -> Path:
        """Absolute path of a path given in the project file (relative to ``root``)."""
        p = Path(rel).expanduser()
        return p if p.is_absolute() else (self.root / p)


# ---------------------------------------------------------------------------------------------
# dict <-> dataclass, with type checks that name the offending key


def _check(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check(value, a, where)
            except ParameterError as e:
                errors.append(e)
        raise errors[0]
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ParameterError(f"{where}: expected a table, got {value!r}")
        return _from_dict(tp, value, where)
    if origin is list:
        if not isinstance(value, list):
            raise ParameterError(f"{where}: expected a list, got {value!r}")
        return [_check(v, args[0], f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ParameterError(f"{where}: expected a table, got {value!r}")
        return dict(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParameterError(f"{where}: expected a whole number, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ParameterError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ParameterError(f"{where}: expected text in quotes, got {value!r}")
        return value
    raise TypeError(f"unsupported type {tp} at {where}")


def _from_dict(cls: type, data: dict, where: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.metadata.get("saved", True)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        known = ", ".join(fields)
        prefix = f"{where}." if where else ""
        raise ParameterError(
            f"unknown key {prefix}{unknown[0]} (known keys{' in [' + where + ']' if where else ''}: {known})"
        )
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _check(value, hints[name], f"{where}.{name}" if where else name)
    return cls(**kwargs)


def _to_dict(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        out = {}
        for f in dataclasses.fields(obj):
            if not f.metadata.get("saved", True):
                continue
            v = getattr(obj, f.name)
            if v is None:
                continue
            out[f.name] = _to_dict(v)
        return out
    if isinstance(obj, list):
        return [_to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _to_dict(v) for k, v in obj.items() if v is not None}
    return obj


def project_from_dict(data: dict, root: Path | str = ".") -> Project:
    """Build a Project from parsed TOML. Raises ParameterError naming the bad key."""
    proj = _from_dict(Project, data, "")
    proj.root = Path(root)
    return proj


def project_to_dict(project: Project) -> dict:
    """The TOML-ready dict of a Project (None fields left out)."""
    return _to_dict(project)


def _parse_toml(path: Path) -> dict:
    """The parsed TOML of a project file in any encoding fieldtool reads (see ``textfile``)."""
    text = read_text(path, "project file")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputFileError(f"{path}: not valid TOML ({e}). Fix the line named, or re-create it.") from e
    except RecursionError:
        raise InputFileError(f"{path}: values nested too deeply to be a project file; fix or re-create it") from None


def load_project(path: Path | str) -> Project:
    """Read a project file. Errors name the file and the key."""
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: project file not found. Create one with `fieldtool init DIR`.")
    data = _parse_toml(path)
    try:
        return project_from_dict(data, path.resolve().parent)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from e
    except RecursionError:
        raise ParameterError(f"{path}: values nested too deeply; fix or re-create the file") from None


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: never half a file.

    A link is followed (its target is replaced, not the link), and a device or pipe (``/dev/stdout``, a FIFO)
    is written straight through: a rename would put a plain file in its place."""
    path = Path(path)
    if path.is_symlink():
        path = path.resolve()
    if path.exists() and not path.is_file() and not path.is_dir():
        with open(path, "wb") as fh:
            fh.write(data)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; results are for others to read too
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


@contextlib.contextmanager
def atomic_path(path: Path | str, mode: int = 0o644):
    """A temporary file name beside ``path`` for a library that writes by file name (netCDF4, GDAL); renamed
    onto ``path`` when the block ends without error, removed otherwise: never half a file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f"{path.suffix}.tmp", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _merge_into(doc: Any, new: dict) -> None:
    """Make the tomlkit container ``doc`` hold ``new``, touching only what differs (comments, order
    and layout of everything else survive)."""
    for k in [k for k in list(doc.keys()) if k not in new]:
        del doc[k]
    for k, v in new.items():
        if k in doc and isinstance(v, dict) and hasattr(doc[k], "keys") and not isinstance(doc[k], list):
            _merge_into(doc[k], v)
        elif k not in doc or _plain(doc[k]) != v:
            doc[k] = _inline(v)


def _inline(v: Any) -> Any:
    """Lists of tables as inline arrays (``filters = [{name = "clahe"}]``), so that they stay where
    the key is, with its comment, instead of moving to an array of tables."""
    if isinstance(v, list) and any(isinstance(x, dict) for x in v):
        arr = tomlkit.array()
        for x in v:
            if isinstance(x, dict):
                t = tomlkit.inline_table()
                t.update({kk: _inline(vv) for kk, vv in x.items()})
                arr.append(t)
            else:
                arr.append(_inline(x))
        return arr
    return v


def _plain(v: Any) -> Any:
    return v.unwrap() if hasattr(v, "unwrap") else v


def _dump_roundtrip(path: Path, data: dict) -> bytes:
    """TOML bytes of ``data``, keeping the comments and layout of the file at ``path`` if it parses."""
    try:
        doc = tomlkit.parse(read_text(path, "project file")) if path.exists() else None
    except Exception:  # noqa: BLE001 - an unreadable old file is replaced by a plain new one
        doc = None
    if doc is None:
        return tomli_w.dumps(data).encode("utf-8")
    _merge_into(doc, data)
    return tomlkit.dumps(doc).encode("utf-8")


class _DirLock:
    """An exclusive lock on the project file's folder (flock), held while re-reading, merging and
    writing, so that two fieldtool processes never interleave their saves."""

    def __init__(self, path: Path):
        self.dir = path.resolve().parent
        self.fd: int | None = None

    def __enter__(self):
        try:
            if fcntl is None:
                raise ImportError("no fcntl here (Windows): saves are not locked")
            self.fd = os.open(self.dir, os.O_RDONLY)
            fcntl.flock(self.fd, fcntl.LOCK_EX)
        except (ImportError, OSError):
            if self.fd is not None:
                os.close(self.fd)
            self.fd = None
        return self

    def __exit__(self, *exc):
        if self.fd is not None:
            os.close(self.fd)  # closing releases the flock
        return False


def save_project(project: Project, path: Path | str) -> None:
    """Write the whole project file atomically (temp file + rename), keeping the comments and
    layout of the file already there. To change some keys while other processes may edit the same
    file, use ``project.sync.ProjectSync``."""
    path = Path(path)
    with _DirLock(path):
        atomic_write_bytes(path, _dump_roundtrip(path, project_to_dict(project)))




