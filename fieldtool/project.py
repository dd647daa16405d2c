"""The Project: every input, parameter and pick of one measurement, read and written as TOML.

Each TOML table maps one-to-one to a dataclass below, and each key to a field of the same name.
Units are in the key names (``_m`` metres, ``_s`` seconds, ``_px`` pixels, ``_ms`` m/s).
Relative paths are relative to the folder of the project file. Pixel coordinates are image
coordinates of the raw video frame: x right, y down, origin at the centre of the top-left pixel.

A field set to ``None`` is "not given" and is left out of the file (TOML has no null).
"""

from __future__ import annotations

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

from .errors import InputFileError, ParameterError

Point = list[float]


@dataclass
class VideoCfg:
    """[video] the clip to analyse."""

    path: str = ""  # video file (any format ffmpeg reads), image folder, or glob like "frames/*.png"
    start_s: float = 0.0  # first frame used, seconds from the start of the clip
    end_s: float | None = None  # last frame used (s); None = to the end
    step: int = 1  # use every step-th frame (1 = all)
    frame_interval_s: float | None = None  # image sequences only: time between two images (s)


@dataclass
class CrossSectionCfg:
    """[cross_section] the surveyed bed, station from the left bank to the right bank."""

    path: str = ""  # text/CSV file of "station, elevation" rows in metres; used when shape = ""
    shape: str = ""  # "" (use path) | rectangular | trapezoidal | parabolic | free
    top_width_m: float | None = None  # width at the top of the banks (rectangular, trapezoidal, parabolic)
    bottom_width_m: float | None = None  # trapezoidal: width of the flat bed
    depth_m: float | None = None  # bank top to deepest bed point
    left_station_m: float = 0.0  # reference point: station of the left bank top
    bank_elevation_m: float = 0.0  # reference point: elevation of the bank tops
    points: list[Point] = field(default_factory=list)  # free shape: [[station_m, elevation_m], ...]


@dataclass
class CalibrationCfg:
    """[calibration] lens model from a checkerboard video (see `fieldtool calibrate`)."""

    path: str = ""  # calibration file written by `fieldtool calibrate`; "" = no lens correction
    checkerboard_video: str = ""  # checkerboard video, to run the calibration from the project
    corners: list[int] = field(default_factory=lambda: [9, 6])  # inner corners (columns, rows)
    square_mm: float | None = None  # side of one square (mm)
    n_frames: int = 20  # the video is split in n parts; first frame with a board in each


@dataclass
class StabilizeCfg:
    """[stabilize] register every frame on the first using stable features outside the water."""

    enabled: bool = False
    regions_px: list[list[float]] = field(default_factory=list)  # rectangles [x0, y0, x1, y1]
    water_polygon_px: list[Point] = field(default_factory=list)  # or: polygon around the water to exclude
    model: str = "homography"  # homography | affine
    max_drift_px: float | None = None  # steady drift (px) past which the picture is checked for water; None = half a region side


@dataclass
class OrthoCfg:
    """[ortho] image -> water-plane mapping from ground control points (GCPs).

    GCP order (thesis figure 7.13): P1, P2 on one bank, P3, P4 on the other, going round the
    quadrilateral. distances_m = [L1, L2, L3, L4, L5, L6] = |P1P2|, |P2P3|, |P3P4|, |P4P1|,
    |P1P3|, |P2P4|.
    """

    method: str = "distances"  # distances | world | pose | two_points (nadir, P1 P2 + |P1P2|) | none
    gcp_px: list[Point] = field(default_factory=list)  # [[x, y], ...] pixels, P1..P4 (pose: 6+)
    distances_m: list[float] = field(default_factory=list)  # L1..L6 (method = distances); [|P1P2|] (method = two_points)
    gcp_world_m: list[list[float]] = field(default_factory=list)  # [[X, Y], ...] or [[X, Y, Z], ...] (pose)
    resolution_m: float | None = None  # pixel size of the rectified image (m); None = automatic


@dataclass
class WaterLevelCfg:
    """[water_level] elevation of the water surface, in the cross-section's datum (thesis ch. 5)."""

    method: str = "value"  # value | width | dem | angle_height | image
    value_m: float | None = None  # method = value: typed level (m, datum of the cross-section, not a depth)
    uncertainty_m: float | None = None  # method = value: 1-sigma of the typed level (m); None = 0.01 m
    width_m: float | None = None  # method = width: measured wetted width, water edge to water edge (m)
    width_uncertainty_m: float | None = None  # method = width: 1-sigma of that width (m); None = 0.02 m
    # adapted Hellebaut (DEM of one bank, x across the river = cross-section station, y along the shore)
    dem_path: str = ""  # raster of elevations, any GDAL format (GeoTIFF, .asc, ...; m, datum of the cross-section); row 0 = y_max
    dem_x_m: list[float] = field(default_factory=list)  # [x_min, x_max] of the DEM domain (m, = station)
    dem_y_m: list[float] = field(default_factory=list)  # [y_min, y_max] of the DEM domain (m)
    dem_precision_mm: float | None = None  # DEM pixel size (mm/pixel); checked against domain / size
    dem_compare_m: float | None = None  # length of bank, from the bank end, compared with the section (m); None = all
    dem_section_y_m: float | None = None  # y of the cross-section in the DEM (m); None = median of all rows
    divergence_station_m: float | None = None  # user override of the detected divergence point (station, m)
    # angle and height (two nadir images on one vertical; their heights are solved, not given)
    image1: str = ""  # image taken at the lower height H
    image2: str = ""  # image taken at the higher height H + dh_m
    dh_m: float | None = None  # height difference between the two images (m), e.g. from the drone GPS
    dh_uncertainty_m: float = 0.05  # 1-sigma of dh_m (m)
    pixel_uncertainty_px: float = 2.0  # 1-sigma of one picked water edge (px); also for method = image
    fov_deg: list[float] = field(default_factory=list)  # [x, y, diagonal] FOV (deg) if no calibration; [x] = square pixels
    fov_uncertainty_deg: float = 0.5  # 1-sigma of the FOV (deg)
    edges1_px: list[Point] = field(default_factory=list)  # left and right water edges on image 1 [[x, y], [x, y]]
    edges2_px: list[Point] = field(default_factory=list)  # left and right water edges on image 2
    # image method: left and right water edges on the raw frame, mapped with the ortho mapping
    edges_px: list[Point] = field(default_factory=list)


@dataclass
class RoiCfg:
    """[roi] where PIV runs, and what it must ignore."""

    rect_px: list[float] = field(default_factory=list)  # [x0, y0, x1, y1]; [] = whole frame
    masks_px: list[list[Point]] = field(default_factory=list)  # polygons whose vectors are invalid


@dataclass
class PivCfg:
    """[piv] correlation and validation parameters."""

    engine: str = "fieldtool"  # fieldtool | openpiv
    window_px: int = 32  # interrogation window side (px)
    overlap_px: int = 16  # overlap between windows (px)
    search_px: int | None = None  # search area side (px); None = window_px
    passes: int = 2  # multi-pass with window deformation: first window = window_px * 2**(passes-1); 2 removes the loss-of-pairs bias
    snr_min: float = 1.3  # minimum ratio of the correlation peak to the highest other local maximum
    averaging: str = "ensemble"  # ensemble | mean | median
    max_velocity_ms: float | None = None  # vectors faster than this are invalid (m/s)
    median_threshold: float = 2.0  # normalised local median test threshold
    std_threshold: float = 4.0  # global standard-deviation test (n sigma)
    min_valid_fraction: float = 0.3  # mean/median: a node valid in fewer pairs than this is dropped
    region: str = "section"  # section (a band around the section(s), within the ROI) | roi | full (whole frame)
    all_pairs: bool = False  # true: correlate every pair; false: add pairs until the discharge has converged
    converge_rel_ci: float = 0.005  # stop when the 95 % interval of the mean per-pair Q is within +- this fraction
    min_pairs: int = 30  # fewest pairs before the convergence test


@dataclass
class SectionCfg:
    """[section] section of interest and discharge parameters."""

    points_px: list[Point] = field(default_factory=list)  # 2 image points: left then right water edge
    n_sub: int = 15  # number of subsections
    station_offset_m: float | None = None  # station of the first point; None = left water edge
    alpha: float | None = None  # velocity index; None = 0.8 if mean depth < 2 m else 0.9


@dataclass
class RerunCfg:
    """[rerun] stream to a supervisor. Off by default; rerun's servers listen on all interfaces."""

    mode: str = "off"  # off | save | connect | serve
    path: str = "run.rrd"  # mode = save: file written in the output folder
    url: str = ""  # mode = connect: rerun+http://HOST:PORT/proxy


@dataclass
class Project:
    """One measurement. ``root`` is the folder relative paths are resolved from (not saved)."""

    name: str = "measurement"  # a name for this measurement (station, date)
    site: str = ""  # site this measurement belongs to ("" = none); see `fieldtool site`
    step: str = "cross_section"  # last TUI step visited
    video: VideoCfg = field(default_factory=VideoCfg)
    cross_section: CrossSectionCfg = field(default_factory=CrossSectionCfg)
    calibration: CalibrationCfg = field(default_factory=CalibrationCfg)
    stabilize: StabilizeCfg = field(default_factory=StabilizeCfg)
    ortho: OrthoCfg = field(default_factory=OrthoCfg)
    water_level: WaterLevelCfg = field(default_factory=WaterLevelCfg)
    roi: RoiCfg = field(default_factory=RoiCfg)
    filters: list[dict[str, Any]] = field(default_factory=list)  # ordered stack: [{name = "clahe", ...}]
    piv: PivCfg = field(default_factory=PivCfg)
    section: SectionCfg = field(default_factory=SectionCfg)
    rerun: RerunCfg = field(default_factory=RerunCfg)
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
    if dataclasses.is_dataclass(tp):
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


def load_project(path: Path | str) -> Project:
    """Read a project file. Errors name the file and the key."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: project file not found. Create one with `fieldtool init DIR`.")
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise InputFileError(f"{path}: not valid TOML ({e}). Fix the line named, or re-create it.") from e
    except OSError as e:
        raise InputFileError(f"{path}: cannot be read ({e.strerror}).") from e
    try:
        return project_from_dict(data, path.resolve().parent)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from e


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: never half a file."""
    path = Path(path)
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


def save_project(project: Project, path: Path | str) -> None:
    """Write the project file atomically (temp file + rename)."""
    atomic_write_bytes(path, tomli_w.dumps(project_to_dict(project)).encode("utf-8"))
