"""Cross-section of the river bed: station (m, left bank -> right bank) and bed elevation (m).

Wetted geometry at a water level (elevation in the same datum, m): water edges, wetted width (m),
wetted area (m²), wetted perimeter (m), and the area between two stations (trapezoidal rule with
the water-edge crossings inserted, so it is exact for the piecewise-linear survey).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fieldtool.errors import GeometryError, InputFileError, ParameterError

SHAPES = ("rectangular", "trapezoidal", "parabolic", "free")
MAX_ABS_M = 10_000.0  # |station| and |elevation| beyond 10 km are not a river survey (m)
MAX_RELIEF_PER_WIDTH = 1000.0  # bed relief (highest - lowest point) over the section's width: beyond, a typo
MAX_FILE_BYTES = 10_000_000  # a cross-section file (text or workbook) is at most 10 MB (~400 000 rows)


@dataclass(frozen=True)
class CrossSection:
    """Surveyed bed. ``station`` strictly increasing (m), ``elevation`` (m), same length >= 2."""

    station: np.ndarray
    elevation: np.ndarray

    def __post_init__(self) -> None:
        s = np.asarray(self.station, dtype=float)
        z = np.asarray(self.elevation, dtype=float)
        if s.ndim != 1 or s.shape != z.shape:
            raise GeometryError("cross-section: station and elevation must be two columns of the same length")
        if len(s) < 2:
            raise GeometryError(f"cross-section: {len(s)} point(s); give at least 2 rows of 'station, elevation'")
        if not np.all(np.isfinite(s)) or not np.all(np.isfinite(z)):
            raise GeometryError("cross-section: a station or elevation is not a number")
        bad = np.nonzero(np.diff(s) <= 0)[0]
        if len(bad):
            i = int(bad[0])
            raise GeometryError(
                f"cross-section: station must increase from the left bank to the right bank, "
                f"but row {i + 2} ({s[i + 1]:g} m) does not exceed row {i + 1} ({s[i]:g} m)"
            )
        object.__setattr__(self, "station", s)
        object.__setattr__(self, "elevation", z)

    # -- levels -----------------------------------------------------------------------------
    @property
    def bed_min(self) -> float:
        """Lowest bed elevation (m)."""
        return float(self.elevation.min())

    def check_level(self, level: float) -> None:
        """Raise GeometryError unless ``level`` wets the section without spilling over a bank end."""
        if not np.isfinite(level):
            raise GeometryError("water level: not a number")
        if level <= self.bed_min:
            raise GeometryError(
                f"water level {level:.3f} m is at or below the lowest bed point ({self.bed_min:.3f} m): "
                "give an elevation in the cross-section's datum, not a depth"
            )
        left, right = self.elevation[0], self.elevation[-1]
        if level > left or level > right:
            side = (
                "both banks"
                if (level > left and level > right)
                else ("the left bank" if level > left else "the right bank")
            )
            raise GeometryError(
                f"water level {level:.3f} m is above {side} (left top {left:.3f} m, right top {right:.3f} m): "
                "the water would spill beyond the surveyed section; check the level or extend the survey"
            )

    def wet_polyline(
        self, level: float, s_from: float | None = None, s_to: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Stations (m) and water depths (m, >= 0) between ``s_from`` and ``s_to``, with every
        water-edge crossing and both limits inserted, so depth is linear between nodes."""
        s, z = self.station, self.elevation
        d = level - z
        pts_s = [s]
        # crossings where depth changes sign inside a segment
        sign_change = np.nonzero((d[:-1] * d[1:]) < 0)[0]
        if len(sign_change):
            t = d[sign_change] / (d[sign_change] - d[sign_change + 1])
            pts_s.append(s[sign_change] + t * (s[sign_change + 1] - s[sign_change]))
        lo = s[0] if s_from is None else float(s_from)
        hi = s[-1] if s_to is None else float(s_to)
        pts_s.append(np.array([lo, hi]))
        ss = np.unique(np.concatenate(pts_s))
        ss = ss[(ss >= lo) & (ss <= hi)]
        depth = level - np.interp(ss, s, z)
        depth[depth < 1e-9] = 0.0  # crossings are exactly dry, despite rounding
        return ss, depth

    def water_edges(self, level: float) -> tuple[float, float]:
        """Stations (m) of the left and right water edges: the outermost dry-to-wet crossings."""
        self.check_level(level)
        ss, depth = self.wet_polyline(level)
        wet = np.nonzero(depth > 0)[0]
        i0, i1 = wet[0], wet[-1]
        return float(ss[max(i0 - 1, 0)]), float(ss[min(i1 + 1, len(ss) - 1)])

    def wetted_width(self, level: float) -> float:
        """Total width of water surface (m), islands excluded."""
        self.check_level(level)
        ss, depth = self.wet_polyline(level)
        seg_wet = (depth[:-1] > 0) | (depth[1:] > 0)
        return float(np.sum(np.diff(ss)[seg_wet]))

    def wetted_area(self, level: float, s_from: float | None = None, s_to: float | None = None) -> float:
        """Wetted area (m²) between two stations (default: the whole section)."""
        ss, depth = self.wet_polyline(level, s_from, s_to)
        return float(np.trapezoid(depth, ss)) if len(ss) > 1 else 0.0

    def wetted_perimeter(self, level: float) -> float:
        """Length of wetted bed (m)."""
        self.check_level(level)
        ss, depth = self.wet_polyline(level)
        zz = np.interp(ss, self.station, self.elevation)
        seg_wet = (depth[:-1] > 0) | (depth[1:] > 0)
        return float(np.sum(np.hypot(np.diff(ss), np.diff(zz))[seg_wet]))

    def depth_at(self, level: float, stations: np.ndarray) -> np.ndarray:
        """Water depth (m, >= 0) at the given stations."""
        return np.clip(level - np.interp(stations, self.station, self.elevation), 0.0, None)


# ---------------------------------------------------------------------------------------------
# creation


def from_shape(
    shape: str,
    *,
    top_width_m: float | None = None,
    bottom_width_m: float | None = None,
    depth_m: float | None = None,
    left_station_m: float = 0.0,
    bank_elevation_m: float = 0.0,
    points: list | None = None,
    n_parabola: int = 41,
) -> CrossSection:
    """Build a cross-section from a shape. The reference point is the left bank top
    (``left_station_m``, ``bank_elevation_m``); widths and depth in metres."""
    shape = shape.lower()
    if shape == "free":
        pts = np.asarray(points or [], dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise GeometryError("cross_section.points: give [[station_m, elevation_m], ...] for a free shape")
        pts, _ = _walls(pts, list(range(len(pts))))  # as a file's rows: a repeat dropped, a wall's points apart
        return CrossSection(pts[:, 0], pts[:, 1])
    if shape not in SHAPES:
        raise ParameterError(f"cross_section.shape: {shape!r} is not one of {', '.join(SHAPES)}")
    for name, v in (("top_width_m", top_width_m), ("depth_m", depth_m)):
        if v is None or not v > 0:
            raise ParameterError(f"cross_section.{name}: a positive number is needed for a {shape} section")
    assert top_width_m is not None and depth_m is not None  # checked just above
    s0, zt, W, D = left_station_m, bank_elevation_m, float(top_width_m), float(depth_m)
    if shape == "rectangular":
        eps = 1e-6 * W
        st: list[float] | np.ndarray = [s0, s0 + eps, s0 + W - eps, s0 + W]
        el: list[float] | np.ndarray = [zt, zt - D, zt - D, zt]
    elif shape == "trapezoidal":
        if bottom_width_m is None or not (0 < bottom_width_m < W):
            raise ParameterError("cross_section.bottom_width_m: give a bed width between 0 and top_width_m")
        slope_w = (W - bottom_width_m) / 2
        st = [s0, s0 + slope_w, s0 + slope_w + bottom_width_m, s0 + W]
        el = [zt, zt - D, zt - D, zt]
    else:  # parabolic: z = zt - D * (1 - (2u/W - 1)^2)
        u = np.linspace(0.0, W, n_parabola)
        st = s0 + u
        el = zt - D * (1.0 - (2.0 * u / W - 1.0) ** 2)
    return CrossSection(np.asarray(st, float), np.asarray(el, float))


# ---------------------------------------------------------------------------------------------
# files

# Units a header may name for a column, with their factor to metres.
_UNITS = {
    "m": 1.0,
    "metre": 1.0,
    "meter": 1.0,
    "metres": 1.0,
    "meters": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "ft": 0.3048,
    "feet": 0.3048,
}
_STATION_NAMES = ("station", "distance", "dist", "chainage", "abscissa", "offset", "x", "s", "afstand", "abscisse")
_ELEVATION_NAMES = ("elevation", "elev", "z", "height", "altitude", "level", "bed", "cote", "hoogte", "niveau")
_DECIMAL_COMMA = re.compile(r"^[+-]?\d+,\d+(?:[eE][+-]?\d+)?$")
_NUMBER = re.compile(r"^[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?$")


def _split_fields(lines: list[str]) -> tuple[str, bool]:
    """Field separator (';', tab, ',' or whitespace) and whether commas are decimal marks.

    Spreadsheets in the European style write ``0,5;10,2`` (semicolons between fields, decimal commas);
    tab-separated exports may carry decimal commas too. A comma is a field separator only when no
    semicolon or tab separates the fields.
    """
    sample = [ln for ln in lines if ln.strip()][:50]
    if any(";" in ln for ln in sample):
        sep = ";"
    elif any("\t" in ln for ln in sample):
        sep = "\t"
    elif any("," in ln for ln in sample):
        sep = ","
    else:
        sep = " "
    comma_decimal = sep in (";", "\t", " ") and any(
        _DECIMAL_COMMA.match(f.strip()) for ln in sample for f in _fields(ln, sep)
    )
    return sep, comma_decimal


def _fields(line: str, sep: str) -> list[str]:
    if sep == " ":
        return line.split()
    out = []
    for f in line.split(sep):
        parts = f.split()
        # tabs and spaces mixed in a data row ("0 5<TAB>1"): numbers split on any white space
        if sep == "\t" and len(parts) > 1 and all(_NUMBER.match(p.replace(",", ".")) for p in parts):
            out += parts
        else:
            out.append(f.strip())
    return out


def _number(cell: str, comma_decimal: bool) -> float | None:
    c = cell.strip().strip('"').strip("'")
    if comma_decimal:
        c = c.replace(",", ".")
    if not _NUMBER.match(c):
        return None
    return float(c)


def _header_columns(cells: list[str], source: str, lineno: int) -> tuple[int, int, float, float]:
    """Columns of station and elevation, and their unit factors, named by a header line."""
    names = [c.strip().strip('"').lower() for c in cells]
    unit = []
    for n in names:
        m = re.search(r"[\(\[]\s*([a-z]+)\s*[\)\]]|[_ ]([a-z]+)$", n)
        u = (m.group(1) or m.group(2)) if m else None
        if u is not None and m is not None and u not in _UNITS and m.group(1):
            raise InputFileError(f"{source}, line {lineno}: unit {u!r} in the header is not one of m, cm, mm, ft")
        unit.append(_UNITS.get(u, 1.0) if u else 1.0)
    words = [re.split(r"[\s_\(\[]+", n)[0] for n in names]
    if any(w.startswith("depth") or w in ("diepte", "profondeur") for w in words) and not any(
        w in _ELEVATION_NAMES for w in words
    ):
        raise InputFileError(
            f"{source}, line {lineno}: the header names a depth column; give bed elevations "
            "(m, in the datum of the water level), not depths"
        )
    si = next((i for i, w in enumerate(words) if w in _STATION_NAMES), 0)
    zi = next((i for i, w in enumerate(words) if w in _ELEVATION_NAMES and i != si), 1 if si == 0 else 0)
    return si, zi, unit[si] if si < len(unit) else 1.0, unit[zi] if zi < len(unit) else 1.0


def parse_rows(rows: list[tuple[int, list[str]]], source: str, comma_decimal: bool = False) -> CrossSection:
    """Cross-section from rows of cells ``(line_number, [cell, ...])``: header lines optional (they may
    name the columns and their units, e.g. ``Station (m); Elevation (cm)``); one "station, elevation"
    pair per data row. Raises InputFileError naming the line of the first row it cannot read."""
    pts: list[tuple[float, float]] = []
    lines: list[int] = []  # the line of each point
    si, zi, fs, fz = 0, 1, 1.0, 1.0
    width = None
    for lineno, cells in rows:
        cells = [c for c in cells if c.strip() != ""] if len(cells) > 2 else cells
        if not cells:
            continue
        vals = [_number(c, comma_decimal) for c in cells]
        if any(v is None for v in vals):
            if not pts and not any(v is not None for v in vals):  # a header line
                si, zi, fs, fz = _header_columns(cells, source, lineno)
                continue
            bad = next(c for c, v in zip(cells, vals, strict=True) if v is None)
            hint = " (use a decimal point, or ';' between fields when the decimals are commas)" if "," in bad else ""
            raise InputFileError(
                f"{source}, line {lineno}: {bad!r} is not a number; expected 'station, elevation' in metres{hint}"
            )
        if len(vals) < 2 or max(si, zi) >= len(vals):
            raise InputFileError(
                f"{source}, line {lineno}: expected two numbers 'station, elevation', got {' '.join(cells)!r}"
            )
        if width is None:
            width = len(vals)
        elif len(vals) != width:
            raise InputFileError(
                f"{source}, line {lineno}: {len(vals)} fields where the rows above have {width}; "
                "check the separators (a decimal comma in a comma-separated file splits a number)"
            )
        st, z = vals[si], vals[zi]
        assert st is not None and z is not None  # rows with a non-number were rejected above
        st_m, z_m = st * fs, z * fz
        for what, v in (("station", st_m), ("elevation", z_m)):
            if not abs(v) <= MAX_ABS_M:
                raise InputFileError(
                    f"{source}, line {lineno}: {what} {v:g} m is beyond ±10 km ({MAX_ABS_M:g} m); "
                    "give the survey in metres (a local datum if the numbers are large)"
                )
        pts.append((st_m, z_m))
        lines.append(lineno)
    if len(pts) < 2:
        raise InputFileError(
            f"{source}: {len(pts)} data row(s); a cross-section needs at least 2 rows of 'station, elevation' in metres"
        )
    arr, lines = _walls(np.asarray(pts), lines)
    _check_relief(arr, lines, source)
    try:
        return CrossSection(arr[:, 0], arr[:, 1])
    except GeometryError as e:
        raise InputFileError(f"{source}: {e}") from e


#: m: the points of a vertical face (a wall, an abutment: rows at one station) are set this far apart, in the order
#: given (the area this moves is this times the face's height: 1 mm x 2 m = 0.002 m²)
WALL_STEP_M = 0.001


def _walls(arr: np.ndarray, lines: list[int]) -> tuple[np.ndarray, list[int]]:
    """A survey's repeated rows and vertical faces, as the section needs them (station increasing): a row that
    repeats the one above (same station and elevation, a point read twice) is dropped; rows at the station of
    the row above with another elevation (down a wall on the left bank, up one on the right) are moved
    :data:`WALL_STEP_M` apart each, in their order. Every row at one station is no section: left as given, and
    refused (a bed that high over a 0 m wide section, as before walls were taken)."""
    keep = [0] + [i for i in range(1, len(arr)) if not np.array_equal(arr[i], arr[i - 1])]
    arr, lines = arr[keep].copy(), [lines[i] for i in keep]
    given = arr[:, 0].copy()
    if given.min() == given.max():
        return arr, lines
    for i in range(1, len(arr)):
        if given[i] == given[i - 1]:
            arr[i, 0] = arr[i - 1, 0] + WALL_STEP_M
    return arr, lines


def _check_relief(arr: np.ndarray, lines: list[int], source: str) -> None:
    """Refuse a bed whose relief exceeds :data:`MAX_RELIEF_PER_WIDTH` times the section's width (a bank 5 km
    high over a 2 m wide section is a typo), naming the line farthest from the median elevation."""
    width = float(arr[:, 0].max() - arr[:, 0].min())
    z = arr[:, 1]
    relief = float(z.max() - z.min())
    if width > 0 and relief <= MAX_RELIEF_PER_WIDTH * width:
        return
    if width <= 0 and relief == 0:
        return  # one station: refused below with its own message
    k = int(np.argmax(np.abs(z - np.median(z))))
    ratio = f"{relief / width:.0f} times" if width > 0 else "infinitely"
    raise InputFileError(
        f"{source}, line {lines[k]}: elevation {z[k]:g} m makes the bed {relief:g} m high over a "
        f"{width:g} m wide section ({ratio} its width; at most {MAX_RELIEF_PER_WIDTH:g}); "
        "check this row's number and unit"
    )


def file_size_problem(path: Path | str) -> str | None:
    """Why a cross-section file is too large to read (over :data:`MAX_FILE_BYTES`), or None."""
    try:
        size = Path(path).stat().st_size
    except OSError:
        return None
    if size <= MAX_FILE_BYTES:
        return None
    return (
        f"{path}: {size / 1e6:.1f} MB; a cross-section file is at most {MAX_FILE_BYTES / 1e6:g} MB "
        "(about 400 000 rows); give the surveyed points of the section only"
    )


def parse_xy_text(text: str, source: str = "cross-section") -> CrossSection:
    """Parse rows of "station, elevation" text in the styles spreadsheets export: comma, semicolon,
    tab or whitespace between fields; decimal commas with ';' or tab separators; a header line
    (optional) that may name the columns and their units (m, cm, mm, ft); '#' comments ignored."""
    lines = [raw.split("#", 1)[0] for raw in text.splitlines()]
    sep, comma_decimal = _split_fields(lines)
    rows = [(i, _fields(ln, sep)) for i, ln in enumerate(lines, 1) if ln.strip()]
    return parse_rows(rows, source, comma_decimal)


def _spreadsheet_rows(path: Path) -> list[tuple[int, list[str]]]:
    """Cells of the first sheet of an .xlsx/.ods workbook as text rows (row numbers from 1)."""
    import pandas as pd  # lazy: pandas (0.2-0.4 s) only for an .xlsx/.ods cross-section

    engine = "odf" if path.suffix.lower() == ".ods" else "openpyxl"
    try:
        df = pd.read_excel(path, sheet_name=0, header=None, dtype=str, engine=engine)
    except Exception as e:  # noqa: BLE001 - any reader failure is a bad file for the user
        raise InputFileError(f"{path}: cannot be read as a {path.suffix} workbook ({type(e).__name__}: {e})") from e
    rows = []
    for i, rec in enumerate(df.itertuples(index=False), 1):
        cells = ["" if (c is None or (isinstance(c, float) and np.isnan(c))) else str(c) for c in rec]
        while cells and cells[-1] == "":
            cells.pop()
        if cells:
            rows.append((i, cells))
    return rows


def load_cross_section(path: Path | str) -> CrossSection:
    """Read a cross-section file: text/CSV in any of the styles :func:`parse_xy_text` reads (UTF-8,
    else Windows-1252), or the first sheet of an .xlsx/.ods workbook."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: cross-section file not found; give a CSV of 'station, elevation' rows in metres")
    too_big = file_size_problem(path)
    if too_big:
        raise InputFileError(too_big)
    if path.suffix.lower() in (".xlsx", ".xlsm", ".ods"):
        return parse_rows(_spreadsheet_rows(path), str(path))
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputFileError(f"{path}: cannot be read ({e.strerror})") from e
    if b"\0" in data[:4096] and not data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputFileError(f"{path}: a binary file, not a text file of 'station, elevation' rows")
    for enc in ("utf-8-sig", "utf-16") if data.startswith((b"\xff\xfe", b"\xfe\xff")) else ("utf-8-sig", "cp1252"):
        try:
            text = data.decode(enc)
            break
        except UnicodeDecodeError:
            continue
    else:
        text = data.decode("latin-1")
    return parse_xy_text(text, str(path))


def to_csv_text(cs: CrossSection) -> str:
    """CSV text of a cross-section, with a header, that :func:`parse_xy_text` reads back."""
    lines = ["station_m,elevation_m"] + [f"{s:.4f},{z:.4f}" for s, z in zip(cs.station, cs.elevation, strict=True)]
    return "\n".join(lines) + "\n"
