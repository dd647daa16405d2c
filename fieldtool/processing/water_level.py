"""Water level: elevation of the water surface in the cross-section's datum (thesis chapter 5, 9.2.5).

Methods (``WaterLevelCfg.method``):

``value``
    A typed elevation, checked against the section.
``width``
    A measured wetted width (water edge to water edge) -> level (thesis 5.2.1, figure 5.7).
``dem``
    Adapted Hellebaut method (5.1): DEM of one bank vs. the surveyed bed, D(x) = |DEM(x) - bed(x)|,
    local minima, their mean, first minimum not above the mean walking from the river to the bank.
``angle_height``
    Two nadir images from heights H and H + dH (5.2.1): subtended angles of the water width -> width
    (centred closed form, off-centre numerical solution, fallback to the centred one) -> level.
``image``
    Water edges on the working image mapped to the water plane with the ortho mapping (5.2.3) -> level.

Width -> level (5.2.1): a horizontal line is lowered over the section; at each level the water surface
is the set of stations where the bed is below the line. The level returned is the one where the
distance between the outermost water edges (``CrossSection.water_edges``) equals the width. The
width of every single channel (and run of channels) is also tried, so that a width that could be
read between the edges of one channel of a split section is reported as several solutions instead
of silently picking one. Flat (vertical-walled) parts, where many levels share one width, and widths
outside the possible range raise :class:`GeometryError`.

Two deliberate departures from the thesis text, both stated where they are used:

- the angle subtended by the water in a nadir image is computed for a rectilinear (pinhole) camera,
  ``theta = atan(u / f)`` with ``f = (N_px / 2) / tan(FOV / 2)``, the model the thesis says it
  assumes; its ``alpha = FOV * Pix_L / Pix_img`` is the small-angle form of it (about 10 % off in
  ``tan(alpha / 2)`` for a river filling half a 70 deg image);
- in the error propagation of ``L = 2 H tan(alpha / 2)`` (5.2.2) the correlated term is
  ``2 (dL/dH)(dL/dalpha) cov(H, alpha)``, which is ``delta_H delta_alpha / (H sin cos)`` relative to
  L squared when fully correlated; the thesis prints it with an extra factor 2.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fieldtool.errors import GeometryError, InputFileError, ParameterError
from fieldtool.processing.cross_section import CrossSection
from fieldtool.processing.ortho import OrthoMapping

if TYPE_CHECKING:  # the configuration's type only: processing/ imports nothing of the project file
    from fieldtool.project.model import WaterLevelCfg


def _argrelextrema(*args, **kwargs):
    """scipy.signal.argrelextrema, imported on first use: scipy.signal costs 0.4-1 s to import and only the
    DEM method needs it."""
    from scipy.signal import argrelextrema

    return argrelextrema(*args, **kwargs)


METHODS = ("value", "width", "dem", "angle_height", "image", "waterline")
DEFAULT_LEVEL_SIGMA_M = 0.01  # method = value, when water_level.uncertainty_m is not given
DEFAULT_WIDTH_SIGMA_M = 0.02  # method = width, when water_level.width_uncertainty_m is not given
FLAT_SLOPE = 0.01  # width changing less than 1 cm per metre of level: the width cannot give the level
SAME_LEVEL_M = 0.001  # solutions closer than this are one solution


@dataclass
class LevelResult:
    """Water level and how sure it is.

    ``level_m``: elevation of the water surface (m, cross-section datum); ``width_m``: distance between
    the outermost water edges at that level (m); ``uncertainty_m``: 1-sigma of the level (m);
    ``method``: value | width | dem | angle_height | image; ``details``: method-specific numbers
    (JSON-serialisable).
    """

    level_m: float
    width_m: float
    uncertainty_m: float
    method: str
    details: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# width <-> level


@dataclass
class _Piece:
    """Levels ``z_lo < z < z_hi`` where the same bed nodes are wet: each water edge moves linearly
    with the level. ``left``/``right``: (a, b) with edge station = a + b * level, one per channel."""

    z_lo: float
    z_hi: float
    left: list[tuple[float, float]]
    right: list[tuple[float, float]]


def _top_level(cs: CrossSection) -> float:
    return float(min(cs.elevation[0], cs.elevation[-1]))


def _pieces(cs: CrossSection) -> list[_Piece]:
    s, z = cs.station, cs.elevation
    top = _top_level(cs)
    levels = np.unique(np.r_[z[(z > cs.bed_min) & (z < top)], cs.bed_min, top])
    out = []
    for z_lo, z_hi in zip(levels[:-1], levels[1:], strict=True):
        wet = z < 0.5 * (z_lo + z_hi)
        idx = np.nonzero(wet)[0]
        runs = np.split(idx, np.nonzero(np.diff(idx) > 1)[0] + 1)
        left, right = [], []
        for r in runs:
            i0, i1 = int(r[0]), int(r[-1])  # first and last wet node; i0 - 1 and i1 + 1 are dry
            a, b = i0 - 1, i0  # edge where the bed, going down from a to b, crosses the level
            k = (s[b] - s[a]) / (z[a] - z[b])
            left.append((s[a] + k * z[a], -k))
            a, b = i1, i1 + 1
            k = (s[b] - s[a]) / (z[b] - z[a])
            right.append((s[a] - k * z[a], k))
        out.append(_Piece(float(z_lo), float(z_hi), left, right))
    return out


def _span_slope(piece: _Piece) -> float:
    """d(outer edge distance)/d(level) in a piece."""
    return piece.right[-1][1] - piece.left[0][1]


def _section_has_flat_walls(pieces: list[_Piece]) -> bool:
    return any(abs(_span_slope(p)) < FLAT_SLOPE for p in pieces)


def width_solutions(cs: CrossSection, width_m: float) -> tuple[list[dict], list[dict]]:
    """Every level at which ``width_m`` separates two water edges.

    Returns ``(solutions, flats)``. A solution is ``{"level_m", "left_m", "right_m", "outer"}``:
    ``outer`` is True when the edges are the outermost ones (the whole water surface), False when
    they bound one channel (or a run of channels) of a split section. ``flats`` lists level ranges
    ``{"from_m", "to_m", "left_m", "right_m"}`` where the width changes by less than
    ``FLAT_SLOPE`` m per metre of level and matches ``width_m``: there the width cannot give the level.
    """
    sols: list[dict] = []
    flats: list[dict] = []
    for p in _pieces(cs):
        n = len(p.left)
        for i in range(n):
            for j in range(i, n):
                a = p.right[j][0] - p.left[i][0]
                b = p.right[j][1] - p.left[i][1]
                w_lo, w_hi = a + b * p.z_lo, a + b * p.z_hi
                tol = 1e-9 * max(1.0, abs(width_m))
                if not (min(w_lo, w_hi) - tol <= width_m <= max(w_lo, w_hi) + tol):
                    continue
                outer = i == 0 and j == n - 1
                if abs(b) < FLAT_SLOPE:
                    zm = 0.5 * (p.z_lo + p.z_hi)
                    flats.append(
                        {
                            "from_m": p.z_lo,
                            "to_m": p.z_hi,
                            "outer": outer,
                            "left_m": p.left[i][0] + p.left[i][1] * zm,
                            "right_m": p.right[j][0] + p.right[j][1] * zm,
                        }
                    )
                    continue
                zs = float(np.clip((width_m - a) / b, p.z_lo, p.z_hi))
                if zs <= cs.bed_min:
                    continue
                sols.append(
                    {
                        "level_m": zs,
                        "left_m": float(p.left[i][0] + p.left[i][1] * zs),
                        "right_m": float(p.right[j][0] + p.right[j][1] * zs),
                        "outer": outer,
                    }
                )
    # the same solution found at the shared end of two pieces counts once
    sols.sort(key=lambda d: (d["level_m"], d["left_m"]))
    merged: list[dict] = []
    for d in sols:
        if merged and abs(d["level_m"] - merged[-1]["level_m"]) < SAME_LEVEL_M:
            merged[-1]["outer"] = merged[-1]["outer"] or d["outer"]
            continue
        merged.append(d)
    return merged, flats


def _width_range(cs: CrossSection) -> tuple[float, float]:
    """Narrowest and widest outer-edge distance over all levels (m)."""
    ws = []
    for p in _pieces(cs):
        a = p.right[-1][0] - p.left[0][0]
        b = _span_slope(p)
        ws += [a + b * p.z_lo, a + b * p.z_hi]
    return float(min(ws)), float(max(ws))


def level_from_width(cs: CrossSection, width_m: float) -> float:
    """Level (m) at which the outermost water edges are ``width_m`` (m) apart (thesis 5.2.1, fig. 5.7).

    Raises
    ------
    GeometryError
        The width is wider than the banks allow, narrower than the narrowest water surface, falls
        where the section has vertical walls (rectangular: many levels share one width), or matches
        several levels (listed in the message).
    """
    if not np.isfinite(width_m) or width_m <= 0:
        raise GeometryError(f"water width {width_m!r} m: give a positive wetted width in metres")
    pieces = _pieces(cs)
    top = _top_level(cs)
    w_min, w_max = _width_range(cs)
    walls = (
        (
            " This section has vertical walls (rectangular): the width does not tell the level there; "
            "type the level (water_level.method = value) or use the DEM method."
        )
        if _section_has_flat_walls(pieces)
        else ""
    )
    if width_m > w_max + 1e-9:
        raise GeometryError(
            f"water width {width_m:.3f} m is wider than the banks: at the lower bank top ({top:.3f} m) the "
            f"water is only {w_max:.3f} m wide. Check the width (edges picked on the banks?) or extend the "
            f"cross-section survey.{walls}"
        )
    sols, flats = width_solutions(cs, width_m)
    if flats:
        lo, hi = min(f["from_m"] for f in flats), max(f["to_m"] for f in flats)
        raise GeometryError(
            f"water width {width_m:.3f} m: every level from {lo:.3f} m to {hi:.3f} m gives this width "
            "(flat-bottomed or vertical-walled, rectangular part of the section), so the width cannot give "
            "the level. Type the level (water_level.method = value) or use the DEM method."
        )
    if not sols:
        if width_m < w_min:
            raise GeometryError(
                f"water width {width_m:.3f} m is narrower than the narrowest water surface of this section "
                f"({w_min:.3f} m, just above the lowest bed point {cs.bed_min:.3f} m). Check the width.{walls}"
            )
        raise GeometryError(
            f"water width {width_m:.3f} m: no level gives exactly this width (the water surface jumps past it "
            "when a separate hollow of the section fills). Check the width or type the level."
        )
    if len(sols) > 1:
        listed = "; ".join(
            f"{d['level_m']:.3f} m (edges at stations {d['left_m']:.2f} and {d['right_m']:.2f} m"
            f"{'' if d['outer'] else ', one channel only'})"
            for d in sols
        )
        raise GeometryError(
            f"water width {width_m:.3f} m matches {len(sols)} levels: {listed}. "
            "Type the right one as water_level.value_m with method = value."
        )
    if not sols[0]["outer"]:
        d = sols[0]
        raise GeometryError(
            f"water width {width_m:.3f} m matches only the width of one channel, at level {d['level_m']:.3f} m "
            f"(edges at stations {d['left_m']:.2f} and {d['right_m']:.2f} m), not the whole water surface. "
            "If those are the edges you picked, type that level (method = value)."
        )
    return sols[0]["level_m"]


def width_at_level(cs: CrossSection, level_m: float) -> float:
    """Distance between the outermost water edges at ``level_m`` (m)."""
    left, right = cs.water_edges(level_m)
    return right - left


def width_slope(cs: CrossSection, level_m: float) -> float:
    """d(width)/d(level) of the outer-edge distance at ``level_m`` (dimensionless); at a bed-node
    elevation, the mean of the slopes just below and just above."""
    slopes = []
    for p in _pieces(cs):
        if p.z_lo - 1e-9 <= level_m <= p.z_hi + 1e-9:
            slopes.append(_span_slope(p))
    if not slopes:
        raise GeometryError(
            f"water level {level_m:.3f} m is outside the section ({cs.bed_min:.3f} to {_top_level(cs):.3f} m)"
        )
    return float(np.mean(slopes))


def level_uncertainty_from_width(cs: CrossSection, level_m: float, width_sigma_m: float) -> float:
    """1-sigma of the level (m) from the 1-sigma of the width (m): ``sigma_w / |d width / d level|``."""
    k = abs(width_slope(cs, level_m))
    if k < FLAT_SLOPE:
        raise GeometryError(
            f"at level {level_m:.3f} m the width hardly changes with the level (vertical walls): "
            "the width cannot give the level; type it (method = value)"
        )
    return float(width_sigma_m / k)


def _from_width(cs: CrossSection, width_m: float, width_sigma_m: float, method: str, details: dict) -> LevelResult:
    level = level_from_width(cs, width_m)
    sigma = level_uncertainty_from_width(cs, level, width_sigma_m)
    left, right = cs.water_edges(level)
    details = {
        **details,
        "measured_width_m": float(width_m),
        "width_uncertainty_m": float(width_sigma_m),
        "water_edges_m": [left, right],
        "dwidth_dlevel": width_slope(cs, level),
    }
    return LevelResult(float(level), float(right - left), sigma, method, details)


# ---------------------------------------------------------------------------------------------
# adapted Hellebaut (DEM)


MAX_DEM_CELLS = 200_000_000  # 1.6 GB as float64: a bank DEM larger than this is to be cropped first


def _rasterio():
    """rasterio, imported on first use: it costs 0.1-0.3 s to import (GDAL) and only the DEM method reads a raster."""
    import rasterio

    return rasterio


def dem_size(path: Path) -> tuple[int, int]:
    """(width, height) in cells of a DEM raster, from its header alone (GDAL's warnings silenced); raises what
    rasterio raises for a file that is not a raster."""
    rasterio = _rasterio()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path) as ds:
            return ds.width, ds.height


def read_dem(path: Path) -> np.ndarray:
    """Elevations (m) of a DEM in any raster format GDAL reads (GeoTIFF, ASCII grid, IMG, VRT, ...), as
    float, its no-data value and non-finite cells as NaN; first band. The size is checked from the header
    before any cell is read."""
    rasterio = _rasterio()
    NotGeoreferencedWarning, RasterioIOError = rasterio.errors.NotGeoreferencedWarning, rasterio.errors.RasterioIOError
    if not path.is_file():
        raise InputFileError(
            f"{path}: DEM file not found (water_level.dem_path); give a raster of elevations in metres"
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                if ds.width * ds.height > MAX_DEM_CELLS:
                    raise InputFileError(
                        f"{path}: the DEM header says {ds.width}x{ds.height} cells, more than "
                        f"{MAX_DEM_CELLS:,}; crop it to the bank near the section"
                    )
                arr = ds.read(1, masked=True).astype(float).filled(np.nan)
    except RasterioIOError as e:
        raise InputFileError(
            f"{path}: cannot read this DEM as a raster ({e}); export it as a GeoTIFF of elevations"
        ) from e
    arr[~np.isfinite(arr)] = np.nan
    return arr


def dem_profile(
    dem: np.ndarray,
    x_m: list[float],
    y_m: list[float],
    precision_mm: float | None,
    cs: CrossSection,
    section_y_m: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """DEM elevations (m) along the cross-section, at the DEM pixel centres inside the section.

    Columns run from ``x_m[0]`` to ``x_m[1]`` (x across the river, the station axis), rows from
    ``y_m[1]`` (row 0) down to ``y_m[0]``. With ``section_y_m`` the nearest row is used, otherwise the
    median of all rows (vegetation and noise along the shore average out). Returns ``(station, dem)``.
    """
    if len(x_m) != 2 or len(y_m) != 2 or not x_m[1] > x_m[0] or not y_m[1] > y_m[0]:
        raise ParameterError(
            "water_level.dem_x_m / dem_y_m: give [min, max] in metres for x (across the river, "
            "the cross-section's station) and y (along the shore), min < max"
        )
    rows, cols = dem.shape
    dx = (x_m[1] - x_m[0]) / cols
    if precision_mm is not None:
        if not precision_mm > 0:
            raise ParameterError("water_level.dem_precision_mm: must be a positive pixel size (mm/pixel)")
        if abs(dx * 1000 - precision_mm) > 0.1 * precision_mm:
            raise ParameterError(
                f"water_level.dem_precision_mm = {precision_mm:g} mm/pixel does not match the DEM: its x domain "
                f"{x_m[1] - x_m[0]:g} m over {cols} columns is {dx * 1000:.3g} mm/pixel. "
                "Check the domain or the precision."
            )
    xs = x_m[0] + (np.arange(cols) + 0.5) * dx
    if section_y_m is not None:
        dy = (y_m[1] - y_m[0]) / rows
        r = int(round((y_m[1] - section_y_m) / dy - 0.5))
        if not 0 <= r < rows:
            raise ParameterError(f"water_level.dem_section_y_m = {section_y_m:g} m is outside the DEM's y domain {y_m}")
        prof = dem[r]
    else:
        with np.errstate(all="ignore"):
            prof = np.nanmedian(dem, axis=0) if np.isfinite(dem).any() else np.full(cols, np.nan)
    keep = (xs >= cs.station[0]) & (xs <= cs.station[-1]) & np.isfinite(prof)
    if keep.sum() < 5:
        raise GeometryError(
            f"the DEM x domain {x_m} m hardly overlaps the cross-section (stations {cs.station[0]:g} to "
            f"{cs.station[-1]:g} m) or has no data there; x must be in the section's station axis"
        )
    return xs[keep], prof[keep]


def hellebaut_divergence(station: np.ndarray, dem: np.ndarray, bed: np.ndarray, compare_m: float | None = None) -> dict:
    """Divergence point of the DEM and bed profiles by the minima algorithm (thesis 5.1.2).

    ``D(x) = |DEM(x) - bed(x)|``; the bank side is the half where D is smaller. Only the ``compare_m``
    metres from the bank end are kept. The local minima of D (``argrelextrema``) and their mean
    are computed; walking from the river to the bank, the first minimum below the mean is the
    divergence point. Returns a dict with ``station_m, d_m, bank ("left" | "right"), minima_idx,
    threshold_m, index`` (into the kept arrays, ``station_m`` etc.), ``dem_m, bed_m``.
    """
    d = np.abs(dem - bed)
    half = len(d) // 2
    bank = "left" if np.mean(d[:half]) <= np.mean(d[half:]) else "right"
    if compare_m is not None:
        if not compare_m > 0:
            raise ParameterError("water_level.dem_compare_m: must be a positive length (m)")
        keep = (station <= station[0] + compare_m) if bank == "left" else (station >= station[-1] - compare_m)
        station, dem, bed, d = station[keep], dem[keep], bed[keep], d[keep]
    minima = _argrelextrema(d, np.less)[0]
    if len(minima) == 0:
        raise GeometryError(
            "DEM method: D(x) = |DEM - bed| has no local minimum over the compared stretch; "
            "give the divergence point as water_level.divergence_station_m"
        )
    threshold = float(np.mean(d[minima]))
    walk = minima[::-1] if bank == "left" else minima  # from the river towards the bank
    chosen = int(next(i for i in walk if d[i] <= threshold))
    return {
        "station_m": station,
        "d_m": d,
        "dem_m": dem,
        "bed_m": bed,
        "bank": bank,
        "minima_idx": minima,
        "threshold_m": threshold,
        "index": chosen,
    }


def _dem_level(cfg: WaterLevelCfg, cs: CrossSection, root: Path) -> LevelResult:
    if not cfg.dem_path:
        raise ParameterError("water_level.dem_path: give the TIFF of the bank's DEM for method = dem")
    p = Path(cfg.dem_path).expanduser()
    dem = read_dem(p if p.is_absolute() else root / p)
    st, prof = dem_profile(dem, cfg.dem_x_m, cfg.dem_y_m, cfg.dem_precision_mm, cs, cfg.dem_section_y_m)
    bed = np.interp(st, cs.station, cs.elevation)
    auto = hellebaut_divergence(st, prof, bed, cfg.dem_compare_m)
    s_auto = float(auto["station_m"][auto["index"]])
    s_div = s_auto if cfg.divergence_station_m is None else float(cfg.divergence_station_m)
    if not cs.station[0] <= s_div <= cs.station[-1]:
        raise ParameterError(
            f"water_level.divergence_station_m = {s_div:g} m is outside the cross-section "
            f"({cs.station[0]:g} to {cs.station[-1]:g} m)"
        )
    level = float(np.interp(s_div, cs.station, cs.elevation))
    cs.check_level(level)
    # resolution of the method: water shallower than the threshold is not told apart from bank; and
    # the edge may lie anywhere from the chosen minimum to one minima spacing beyond the farthest
    # rejected minimum that still looks like bank (D < 3 x threshold): rms distance span / sqrt(3)
    pixel = float(np.median(np.diff(st)))
    mins_st, mins_d = auto["station_m"][auto["minima_idx"]], auto["d_m"][auto["minima_idx"]]
    riverward = (mins_st > s_div) if auto["bank"] == "left" else (mins_st < s_div)
    bank_like = riverward & (mins_d < 3 * auto["threshold_m"])
    spacing = float(np.median(np.diff(mins_st))) if len(mins_st) > 1 else pixel
    span = (float(np.max(np.abs(mins_st[bank_like] - s_div))) if bank_like.any() else 0.0) + spacing
    sigma_station = max(pixel, span / np.sqrt(3))
    h = max(pixel, 1e-3)
    slope = abs(np.interp(s_div + h, cs.station, cs.elevation) - np.interp(s_div - h, cs.station, cs.elevation)) / (
        2 * h
    )
    sigma = float(np.hypot(auto["threshold_m"], slope * sigma_station))
    left, right = cs.water_edges(level)
    k = abs(width_slope(cs, level))
    mins = auto["minima_idx"]
    profile = {
        "station_m": np.round(auto["station_m"], 4).tolist(),
        "dem_m": np.round(auto["dem_m"], 4).tolist(),
        "bed_m": np.round(auto["bed_m"], 4).tolist(),
        "d_m": np.round(auto["d_m"], 4).tolist(),
        "minima_station_m": np.round(auto["station_m"][mins], 4).tolist(),
        "minima_d_m": np.round(auto["d_m"][mins], 4).tolist(),
        "threshold_m": auto["threshold_m"],
        "auto_station_m": s_auto,
        "divergence_station_m": s_div,
    }
    details = {
        "bank": auto["bank"],
        "divergence_station_m": s_div,
        "auto_divergence_station_m": s_auto,
        "overridden": cfg.divergence_station_m is not None,
        "threshold_m": auto["threshold_m"],
        "n_minima": int(len(mins)),
        "dem_pixel_m": pixel,
        "station_uncertainty_m": sigma_station,
        "dem_at_divergence_m": float(np.interp(s_div, auto["station_m"], auto["dem_m"])),
        "water_edges_m": [left, right],
        "width_uncertainty_m": float(sigma * k),
        "dem_profile": profile,
    }
    return LevelResult(level, float(right - left), sigma, "dem", details)


# ---------------------------------------------------------------------------------------------
# angle and height


def fov_axis(angle_deg: float) -> str:
    """FOV axis for a section at ``angle_deg`` to the image x axis (thesis 5.2.1): below 30 deg 'x',
    above 60 deg 'y', else 'diag'."""
    a = abs(float(angle_deg)) % 180.0
    a = min(a, 180.0 - a)
    return "x" if a < 30.0 else ("y" if a > 60.0 else "diag")


def _fov_triplet(fov_deg, shape: tuple[int, int], key: str) -> np.ndarray:
    f = [float(v) for v in fov_deg]
    if len(f) == 1:  # square pixels: the other two follow from the image size
        h, w = shape
        foc = (w / 2) / np.tan(np.radians(f[0]) / 2)
        f = [f[0], np.degrees(2 * np.arctan(h / 2 / foc)), np.degrees(2 * np.arctan(np.hypot(w, h) / 2 / foc))]
    if len(f) != 3 or not all(0 < v < 180 for v in f):
        raise ParameterError(f"{key}: give the field of view [x, y, diagonal] in degrees (0 to 180), or [x] alone")
    return np.array(f)


def _image_angles(edges: np.ndarray, shape: tuple[int, int], fov_rad: np.ndarray) -> dict:
    """Subtended angle of the water and relative shift in one nadir image.

    The edges are projected on the section direction ``d`` through the image centre ``c``:
    ``u = (p - c) . d``, ray angle ``theta = atan(u / f)`` with ``f = (N / 2) / tan(FOV / 2)`` for
    the axis chosen by the section angle (N = width, height or diagonal in pixels).
    Relative shift ``dX / L = ((c - mid) . d) / L_px`` (thesis, figure 5.6).
    """
    h, w = shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    vec = edges[1] - edges[0]
    lpx = float(np.hypot(*vec))
    d = vec / lpx
    angle = float(np.degrees(np.arctan2(vec[1], vec[0])))
    axis = fov_axis(angle)
    n_px = {"x": w, "y": h, "diag": float(np.hypot(w, h))}[axis]
    fov = fov_rad[{"x": 0, "y": 1, "diag": 2}[axis]]
    f = (n_px / 2) / np.tan(fov / 2)
    u = (edges - c) @ d
    theta = np.arctan(u / f)
    return {
        "alpha": float(theta[1] - theta[0]),
        "shift": float((c - edges.mean(axis=0)) @ d / lpx),
        "axis": axis,
        "angle_deg": angle,
        "length_px": lpx,
        "f_px": float(f),
    }


def centred_solution(alpha_low: float, alpha_high: float, dh_m: float) -> tuple[float, float]:
    """Width L and lower height H (m) from eqs. 5.1-5.2 (drone above the river centre):
    ``tan(alpha_high / 2) = (L / 2) / (H + dH)``, ``tan(alpha_low / 2) = (L / 2) / H``."""
    t_low, t_high = np.tan(alpha_low / 2), np.tan(alpha_high / 2)
    if not t_low > t_high > 0:
        raise GeometryError(
            "angle and height: the water must look narrower in the higher image (image2) than in the lower one "
            f"(image1); got {np.degrees(alpha_low):.2f} deg low vs {np.degrees(alpha_high):.2f} deg high. "
            "Check that image1 is the lower one and the edges are picked on both."
        )
    H = dh_m * t_high / (t_low - t_high)
    return float(2 * H * t_low), float(H)


def _subtended(h: float, L: float, shift: float) -> float:
    """alpha = pi - gamma - beta for a camera at height h, shifted by shift * L from the river centre."""
    dx = shift * L
    return float(np.pi - np.arctan2(h, L / 2 - dx) - np.arctan2(h, L / 2 + dx))


def offcentre_solution(
    alpha_low: float, alpha_high: float, dh_m: float, shift: float, guess: tuple[float, float]
) -> tuple[float, float]:
    """Width L and lower height H (m) for a camera shifted by ``shift * L`` from the river centre
    (thesis figure 5.6), solved numerically from ``guess``. Raises GeometryError if it fails."""

    def res(x: np.ndarray) -> np.ndarray:
        L, H = x
        return np.array([_subtended(H, L, shift) - alpha_low, _subtended(H + dh_m, L, shift) - alpha_high])

    from scipy.optimize import least_squares  # lazy: scipy.optimize costs 0.2-0.5 s; only angle_height

    sol = least_squares(
        res, np.asarray(guess, float), bounds=([1e-6, 1e-6], [np.inf, np.inf]), xtol=1e-14, ftol=1e-14, gtol=1e-14
    )
    if not sol.success or np.max(np.abs(sol.fun)) > 1e-9:
        raise GeometryError(f"off-centre solution did not converge (residual {np.max(np.abs(sol.fun)):.2e} rad)")
    return float(sol.x[0]), float(sol.x[1])


def angle_height_width(
    edges1_px,
    edges2_px,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    dh_m: float | None,
    fov_deg,
    *,
    dh_sigma_m: float = 0.05,
    pixel_sigma_px: float = 2.0,
    fov_sigma_deg: float = 0.5,
) -> dict:
    """Wetted width (m) from two nadir images at heights H (image 1) and H + dh (image 2), thesis 5.2.1.

    Returns ``width_m, width_sigma_m, H_m, solution ("off-centre" | "centred"), ...``. The 1-sigma of
    the width is the first-order error propagation (5.2.2) of the independent inputs (dh, FOV, the
    eight edge coordinates) through the solution; ``thesis_width_sigma_m`` is the thesis' two-variable
    form for ``L = 2 H tan(alpha / 2)`` with the correlated term ``2 dL/dH dL/dalpha cov(H, alpha)``
    (identical for the centred solution).
    """
    e1 = np.asarray(edges1_px, float)
    e2 = np.asarray(edges2_px, float)
    for e, key, shp in ((e1, "water_level.edges1_px", shape1), (e2, "water_level.edges2_px", shape2)):
        if e.shape != (2, 2):
            raise ParameterError(f"{key}: pick the two water edges, [[x, y], [x, y]] pixels")
        h, w = shp
        if np.any(e < -0.5) or np.any(e[:, 0] > w - 0.5) or np.any(e[:, 1] > h - 0.5):
            raise GeometryError(f"{key}: a point lies outside the {w}x{h} image")
        if np.hypot(*(e[1] - e[0])) < 2:
            raise GeometryError(f"{key}: the two water edges are the same point; pick the left and the right edge")
    if dh_m is None or not dh_m > 0:
        raise ParameterError("water_level.dh_m: give the height difference between the two images (m, > 0)")
    fov1 = np.radians(_fov_triplet(fov_deg, shape1, "water_level.fov_deg"))
    fov2 = np.radians(_fov_triplet(fov_deg, shape2, "water_level.fov_deg"))

    def solve(q: np.ndarray, mode: str | None = None) -> tuple[float, float, float, str, dict, dict]:
        dh, dfov, pts = q[0], q[1], q[2:].reshape(2, 2, 2)
        a1 = _image_angles(pts[0], shape1, fov1 + dfov)
        a2 = _image_angles(pts[1], shape2, fov2 + dfov)
        Lc, Hc = centred_solution(abs(a1["alpha"]), abs(a2["alpha"]), dh)
        shift = 0.5 * (abs(a1["shift"]) + abs(a2["shift"]))  # alpha is even in the shift; picks may run either way
        if mode in (None, "off-centre"):
            try:
                L, H = offcentre_solution(abs(a1["alpha"]), abs(a2["alpha"]), dh, shift, (Lc, Hc))
                return L, H, abs(a1["alpha"]), "off-centre", a1, a2
            except GeometryError:
                if mode == "off-centre":
                    raise
        return Lc, Hc, abs(a1["alpha"]), "centred", a1, a2

    q0 = np.r_[dh_m, 0.0, e1.ravel(), e2.ravel()]
    L, H, alpha, mode, a1, a2 = solve(q0)
    Lc, Hc = centred_solution(abs(a1["alpha"]), abs(a2["alpha"]), dh_m)
    sig = np.r_[dh_sigma_m, np.radians(fov_sigma_deg), np.full(8, pixel_sigma_px)]
    steps = np.r_[1e-4 * dh_m, 1e-6, np.full(8, 1e-3)]
    J = np.zeros((3, len(q0)))  # rows: L, H, alpha
    for k, step in enumerate(steps):
        qp, qm = q0.copy(), q0.copy()
        qp[k] += step
        qm[k] -= step
        rp, rm = solve(qp, mode), solve(qm, mode)
        J[:, k] = (np.array(rp[:3]) - np.array(rm[:3])) / (2 * step)
    C = (J * sig**2) @ J.T
    sL, sH, sa = np.sqrt(np.diag(C))
    covHa = C[1, 2]
    dLdH, dLda = 2 * np.tan(alpha / 2), H / np.cos(alpha / 2) ** 2
    thesis = np.sqrt(max(dLdH**2 * sH**2 + dLda**2 * sa**2 + 2 * dLdH * dLda * covHa, 0.0))
    return {
        "width_m": L,
        "width_sigma_m": float(sL),
        "H_m": H,
        "solution": mode,
        "centred_width_m": Lc,
        "centred_H_m": Hc,
        "relative_shift": 0.5 * (abs(a1["shift"]) + abs(a2["shift"])),
        "alpha1_deg": float(np.degrees(abs(a1["alpha"]))),
        "alpha2_deg": float(np.degrees(abs(a2["alpha"]))),
        "fov_axis": [a1["axis"], a2["axis"]],
        "section_angle_deg": [a1["angle_deg"], a2["angle_deg"]],
        "length_px": [a1["length_px"], a2["length_px"]],
        "sigma_H_m": float(sH),
        "sigma_alpha_deg": float(np.degrees(sa)),
        "corr_H_alpha": float(covHa / (sH * sa)) if sH > 0 and sa > 0 else 0.0,
        "thesis_width_sigma_m": float(thesis),
    }


def _read_shape(path: Path, key: str) -> tuple[int, int]:
    if not path.is_file():
        raise InputFileError(f"{path}: image not found ({key})")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputFileError(f"{path}: not an image OpenCV can read ({key}); use JPEG, PNG or TIFF")
    return int(img.shape[0]), int(img.shape[1])


def _resolve(root: Path, rel: str) -> Path:
    p = Path(rel).expanduser()
    return p if p.is_absolute() else root / p


# ---------------------------------------------------------------------------------------------
# image method


def image_width(
    edges_px,
    mapping: OrthoMapping,
    pixel_sigma_px: float,
    points_transform: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[float, float, np.ndarray]:
    """Width (m) between two water edges picked on the raw frame, its 1-sigma (m), and the edges on
    the water plane (2, 2) m. The sigma combines ``pixel_sigma_px`` on each edge (through the
    mapping's Jacobian) and the mapping's own RMS residual (m)."""
    e = np.asarray(edges_px, float)
    if e.shape != (2, 2):
        raise ParameterError("water_level.edges_px: pick the two water edges, [[x, y], [x, y]] pixels of the frame")
    if points_transform is not None:
        e = np.asarray(points_transform(e), float).reshape(2, 2)
    world = mapping.image_to_world(e)
    vec = world[1] - world[0]
    width = float(np.hypot(*vec))
    if width <= 0:
        raise GeometryError("water_level.edges_px: the two water edges map to the same point")
    u = vec / width
    J = mapping.jacobian(e[:, 0], e[:, 1])  # (2, 2, 2): d(X, Y)/d(x, y) at each edge
    g = np.einsum("i,kij->kj", u, J)  # d width / d pixel (sign aside) at each edge
    sigma = float(np.sqrt(pixel_sigma_px**2 * np.sum(g**2) + mapping.residual_m**2))
    return width, sigma, world


# ---------------------------------------------------------------------------------------------
# dispatch


def compute_level(
    cfg: WaterLevelCfg,
    cs: CrossSection,
    *,
    root: Path,
    mapping: OrthoMapping | None = None,
    fov_deg: tuple[float, float, float] | None = None,
    points_transform: Callable[[np.ndarray], np.ndarray] | None = None,
    image_undistort: Callable[[np.ndarray, tuple[int, int]], np.ndarray] | None = None,
    detected: dict | None = None,
    station_of: Callable[[np.ndarray], np.ndarray] | None = None,
) -> LevelResult:
    """Water level by ``cfg.method`` (see module docstring).

    Parameters
    ----------
    cfg : the project's [water_level] table.
    cs : the cross-section (station, elevation in m).
    root : folder relative paths (DEM, images) are resolved from.
    mapping : image -> water-plane mapping of the working image (method = image).
    fov_deg : (x, y, diagonal) field of view (deg) from the lens calibration (angle_height); when
        None, ``cfg.fov_deg`` is used.
    points_transform : raw-frame pixels -> working-image pixels (lens undistortion), applied to
        ``cfg.edges_px`` (method = image).
    image_undistort : ``(pts, (H, W)) -> pts`` lens undistortion of pixels of an image of that size
        (angle_height: the pinhole formulas of thesis 5.2.1 need undistorted edges).
    detected : method = waterline: :func:`processing.waterline.detect_water_edges`' result (edges in
        working-image pixels and their 1-sigma), measured on the clip by the caller.
    station_of : method = waterline: water-plane points (N, 2) m -> cross-section stations (m), when the
        section's first point has a surveyed station (see :func:`waterline_level`).
    """
    root = Path(root)
    m = cfg.method
    if m == "value":
        if cfg.value_m is None:
            raise ParameterError("water_level.value_m: type the level (elevation in the cross-section's datum, m)")
        cs.check_level(cfg.value_m)
        sigma = DEFAULT_LEVEL_SIGMA_M if cfg.uncertainty_m is None else float(cfg.uncertainty_m)
        if not sigma >= 0:
            raise ParameterError("water_level.uncertainty_m: must be zero or a positive number of metres")
        left, right = cs.water_edges(cfg.value_m)
        k = abs(width_slope(cs, cfg.value_m))
        details = {
            "uncertainty_source": "default 0.01 m (water_level.uncertainty_m not given)"
            if cfg.uncertainty_m is None
            else "water_level.uncertainty_m",
            "water_edges_m": [left, right],
            "width_uncertainty_m": sigma * k,
        }
        return LevelResult(float(cfg.value_m), float(right - left), sigma, "value", details)
    if m == "width":
        if cfg.width_m is None:
            raise ParameterError("water_level.width_m: give the measured wetted width (m) for method = width")
        sw = DEFAULT_WIDTH_SIGMA_M if cfg.width_uncertainty_m is None else float(cfg.width_uncertainty_m)
        src = (
            "default 0.02 m (water_level.width_uncertainty_m not given)"
            if cfg.width_uncertainty_m is None
            else "water_level.width_uncertainty_m"
        )
        return _from_width(cs, float(cfg.width_m), sw, "width", {"uncertainty_source": src})
    if m == "dem":
        return _dem_level(cfg, cs, root)
    if m == "angle_height":
        if not cfg.image1 or not cfg.image2:
            raise ParameterError(
                "water_level.image1 / image2: give the nadir images taken at the lower (image1) "
                "and the higher (image2) height"
            )
        fov = fov_deg if fov_deg is not None else (cfg.fov_deg or None)
        if fov is None:
            raise ParameterError(
                "angle and height needs the camera's field of view: run the lens calibration "
                "(calibration.path) or give water_level.fov_deg = [x, y, diagonal] in degrees"
            )
        shape1 = _read_shape(_resolve(root, cfg.image1), "water_level.image1")
        shape2 = _read_shape(_resolve(root, cfg.image2), "water_level.image2")
        e1: list | np.ndarray = cfg.edges1_px  # picked points, undistorted into an array when the lens is known
        e2: list | np.ndarray = cfg.edges2_px
        if image_undistort is not None and np.shape(e1) == (2, 2) and np.shape(e2) == (2, 2):
            e1, e2 = image_undistort(np.asarray(e1, float), shape1), image_undistort(np.asarray(e2, float), shape2)
        r = angle_height_width(
            e1,
            e2,
            shape1,
            shape2,
            cfg.dh_m,
            fov,
            dh_sigma_m=cfg.dh_uncertainty_m,
            pixel_sigma_px=cfg.pixel_uncertainty_px,
            fov_sigma_deg=cfg.fov_uncertainty_deg,
        )
        r["fov_source"] = "calibration" if fov_deg is not None else "water_level.fov_deg"
        r["edges_undistorted"] = image_undistort is not None
        return _from_width(cs, r["width_m"], r["width_sigma_m"], "angle_height", r)
    if m == "image":
        if mapping is None:
            raise ParameterError("water_level.method = image needs the orthorectification (ortho.* GCPs) first")
        w, sw, world = image_width(cfg.edges_px, mapping, cfg.pixel_uncertainty_px, points_transform)
        return _from_width(
            cs, w, sw, "image", {"edges_world_m": world.tolist(), "mapping_residual_m": float(mapping.residual_m)}
        )
    if m == "waterline":
        if mapping is None or detected is None:
            raise ParameterError("water_level.method = waterline needs the orthorectification and the clip")
        return waterline_level(cs, mapping, detected, station_of)
    raise ParameterError(f"water_level.method: {m!r} is not one of {', '.join(METHODS)}")


# ---------------------------------------------------------------------------------------------
# waterline: levels of several search lines, checked against each other

WATERLINE_MIN_LINES = 3  # lines with both edges found (of 5) below which the method refuses
WATERLINE_DOUBT_M = 0.02  # the lines' levels scatter more than this (sd, m): doubtful, sigma widened by the scatter
WATERLINE_REFUSE_M = 0.05  # ... more than this, or a level 1-sigma above it: refused
WATERLINE_WEAK_CONTRAST = 6.0  # water less than this many times as active as the quieter bank: doubtful (the
# synthetic scenes give 17-35; wind-blown grass on the Geul clip gives 3.6-4.8 and puts edges in the grass)
WATERLINE_EDGES_K = 3.0  # with section.station_offset_m: the two edges' bank levels differ by more than this times
WATERLINE_EDGES_MIN_M = 0.03  # their combined 1-sigma and this (m): doubtful
REFUSE_FIX = (
    "type the level (water_level.method = value, water_level.value_m) or pick the two water edges on the "
    "frame (water_level.method = image)"
)


def _refuse(why: str) -> GeometryError:
    return GeometryError(
        f"water_level.method = waterline: could not find the water line reliably ({why}); {REFUSE_FIX}"
    )


def _waterline_line(cs: CrossSection, mapping: OrthoMapping, ln: dict) -> dict:
    """One parallel search line's record: its offset (m) and pixels, and either ``error`` or the level (m),
    its 1-sigma (m), the width on the water plane and its 1-sigma (m), the edges in pixels (px, 1-sigma px)
    and on the water plane (m), the activity contrast (ratio) and the still-water pixels."""
    item = {"offset_m": ln["offset_m"], "search_line_px": np.asarray(ln["line_px"]).tolist()}
    if "error" in ln:
        item["error"] = ln["error"]
        return item
    sig = float(np.max(ln["sigma_px"]))
    try:
        w, sw, world = image_width(ln["edges_px"], mapping, sig, None)
        r = _from_width(cs, w, sw, "waterline", {})
    except GeometryError as e:
        item["error"] = str(e)
        return item
    item.update(
        level_m=r.level_m,
        uncertainty_m=r.uncertainty_m,
        width_m=w,
        width_sigma_m=sw,
        edges_px=np.asarray(ln["edges_px"]).tolist(),
        edge_sigma_px=np.asarray(ln["sigma_px"]).tolist(),
        edges_world_m=world.tolist(),
        contrast=ln["contrast"],
        still_water_px=ln["still_water_px"],
    )
    return item


def _waterline_doubts(spread: float, contrast: float, n_lines: int) -> list[dict]:
    """The water line's doubts, in order: lines' scatter ``spread`` (sd, m) over ``WATERLINE_DOUBT_M``,
    median activity ``contrast`` (ratio, water over banks) under ``WATERLINE_WEAK_CONTRAST``, and a
    single search line (``n_lines`` == 1)."""
    doubts = []
    if spread > WATERLINE_DOUBT_M:
        doubts.append(
            {
                "code": "waterline_scatter",
                "value": spread,
                "threshold": WATERLINE_DOUBT_M,
                "message": f"the water line's parallel search lines give levels {100 * spread:.1f} cm apart "
                f"(sd, over {100 * WATERLINE_DOUBT_M:g} cm); its uncertainty includes that scatter",
            }
        )
    if contrast < WATERLINE_WEAK_CONTRAST:
        doubts.append(
            {
                "code": "waterline_weak_contrast",
                "value": contrast,
                "threshold": WATERLINE_WEAK_CONTRAST,
                "message": f"along the water line's search lines the water is only {contrast:.1f} times as active "
                f"as the banks (under {WATERLINE_WEAK_CONTRAST:g}): moving grass or slow water may put an "
                "edge on the wrong side",
            }
        )
    if n_lines == 1:
        doubts.append(
            {
                "code": "waterline_unchecked",
                "value": None,
                "threshold": None,
                "message": "the water line was searched on one line only (water_level.search_spacing_m = 0): "
                "nothing checks it",
            }
        )
    return doubts


def _waterline_edge_levels(
    cs: CrossSection, line: dict, station_of: Callable[[np.ndarray], np.ndarray]
) -> tuple[dict, dict | None]:
    """The median line's two edges as levels on their own: their stations (m), the bed elevations there
    (m), the difference (m) and its tolerance (m, ``WATERLINE_EDGES_K`` times the combined 1-sigma, at
    least ``WATERLINE_EDGES_MIN_M``); and the ``waterline_edges_disagree`` doubt, or None when they agree."""
    st = np.sort(np.asarray(station_of(np.asarray(line["edges_world_m"], float)), float).ravel())
    ez = np.interp(st, cs.station, cs.elevation)
    slope = np.abs(np.gradient(cs.elevation, cs.station))
    ss = line["width_sigma_m"] * np.interp(st, cs.station, slope)  # each edge's station 1-sigma <= the width's
    gap, tol = float(ez[1] - ez[0]), float(max(WATERLINE_EDGES_K * np.hypot(*ss), WATERLINE_EDGES_MIN_M))
    edge_levels = {"stations_m": st.tolist(), "levels_m": ez.tolist(), "difference_m": gap, "tolerance_m": tol}
    if not abs(gap) > tol:  # as written, so a NaN gap gives no doubt
        return edge_levels, None
    doubt = {
        "code": "waterline_edges_disagree",
        "value": abs(gap),
        "threshold": tol,
        "message": "the water line's left and right edges lie on the banks at levels "
        f"{100 * abs(gap):.1f} cm "
        f"apart (over {100 * tol:.1f} cm): an edge is off, or section.station_offset_m is",
    }
    return edge_levels, doubt


def waterline_level(
    cs: CrossSection,
    mapping: OrthoMapping,
    detected: dict,
    station_of: Callable[[np.ndarray], np.ndarray] | None = None,
) -> LevelResult:
    """Level from the water edges found along several parallel search lines
    (:func:`processing.waterline.detect_water_edges`).

    Each line's edges give a width on the water plane (:func:`image_width`) and so a level. In a reach
    where the width changes slowly, lines a few decimetres apart must give the same level: their scatter
    is the self-check. The level is the median of the lines' levels; its 1-sigma combines the median
    line's own 1-sigma and the scatter (sd) between lines.

    Refuses (GeometryError naming ``water_level.method`` and the fix: type the level) when the centre line
    finds no edge, fewer than ``WATERLINE_MIN_LINES`` lines do, or the lines' levels scatter, or the level's
    1-sigma is, more than ``WATERLINE_REFUSE_M``; a scatter above ``WATERLINE_DOUBT_M``, a weak activity contrast
    between water and banks (``WATERLINE_WEAK_CONTRAST``), or a single line, is listed in
    ``details["doubtful"]`` (turned into a quality reason by the caller).

    ``station_of``: water-plane points (N, 2) m -> cross-section stations (m), known when the section's
    first point has a surveyed station (``section.station_offset_m``). Then each edge of the median line
    also gives a level on its own, the bed elevation of its bank at its station, and the two must agree
    (within ``WATERLINE_EDGES_K`` times their combined 1-sigma and ``WATERLINE_EDGES_MIN_M``), else the
    run is doubtful. A station offset that is wrong moves both edges' levels in opposite directions, so
    this check also catches it.
    """
    per = [_waterline_line(cs, mapping, ln) for ln in detected["lines"]]
    ok = [p for p in per if "level_m" in p]
    centre = per[0]
    if "level_m" not in centre:
        raise _refuse(f"on the search line: {centre['error']}")
    if len(per) > 1 and len(ok) < WATERLINE_MIN_LINES:
        raise _refuse(f"only {len(ok)} of {len(per)} parallel search lines found both edges")
    z = np.array([p["level_m"] for p in ok])
    s = np.array([p["uncertainty_m"] for p in ok])
    zm = float(np.median(z))
    spread = float(np.std(z, ddof=1)) if len(z) > 1 else 0.0
    if spread > WATERLINE_REFUSE_M:
        raise _refuse(
            f"the levels of {len(ok)} parallel search lines scatter by {100 * spread:.1f} cm (sd), more "
            f"than {100 * WATERLINE_REFUSE_M:g} cm: the edges are not where the water ends on some of them"
        )
    doubts = _waterline_doubts(spread, float(np.median([p["contrast"] for p in ok])), len(per))
    k = int(np.argmin(np.abs(z - zm)))
    edge_levels = None
    if station_of is not None:
        edge_levels, doubt = _waterline_edge_levels(cs, ok[k], station_of)
        if doubt is not None:
            doubts.append(doubt)
    sigma = float(np.hypot(s[k], spread))
    if sigma > WATERLINE_REFUSE_M:
        raise _refuse(
            f"the level it gives is uncertain by {100 * sigma:.1f} cm (1-sigma), more than "
            f"{100 * WATERLINE_REFUSE_M:g} cm: the edges are seen too obliquely or too blurred to give the level"
        )
    res = _from_width(
        cs,
        ok[k]["width_m"],
        ok[k]["width_sigma_m"],
        "waterline",
        {"lines": per, "n_frames": detected["n_frames"], "mapping_residual_m": float(mapping.residual_m)},
    )
    res.details.update(
        lines_found=len(ok),
        lines_spread_m=spread,
        centre_level_m=centre["level_m"],
        edges_px=ok[k]["edges_px"],
        edge_sigma_px=ok[k]["edge_sigma_px"],
        edges_world_m=ok[k]["edges_world_m"],
        search_line_px=centre["search_line_px"],
        contrast=ok[k]["contrast"],
        edge_levels=edge_levels,
        doubtful=doubts,
    )
    return LevelResult(zm, res.width_m, sigma, "waterline", res.details)
