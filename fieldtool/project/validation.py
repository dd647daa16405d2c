"""The one validation layer of the project file, used by the CLI, the TUI and the viewer.

Every key is checked the same way before any step runs: its type, unit range, finiteness, the
shape of point lists, path rules (length, control characters, a regular readable file where a file
is read: never a pipe, a device or a folder), bounded sizes, and simple geometry (coincident or
collinear GCPs, degenerate ROI and regions). The rules of each key are declared beside the Project
dataclasses (``fieldtool.project.keyspec.key``); an undeclared key is still checked from its type
annotation (finite numbers within +-1e12, non-ragged lists, safe text).

API::

    validate(project, *, files=True) -> list[Problem]     # every problem, in key order
    problems_for(project, prefix, *, files=True) -> list[Problem]  # e.g. "ortho." for one TUI step
    check(project, *, files=True, prefix="")               # raises ParameterError on the first error

``str(problem)`` is the one-line message "key: what is wrong; the fix". ``files=False`` skips
everything that touches the disk (existence, the clip's header, the DEM header).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import stat
import types
import typing
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fieldtool.errors import FieldToolError, ParameterError
from fieldtool.processing.cross_section import MAX_ABS_M, file_size_problem
from fieldtool.processing.filters import FILTERS, FilterStack
from fieldtool.processing.frames import FrameSource
from fieldtool.processing.paths import is_pattern, literal_glob
from fieldtool.processing.water_level import MAX_DEM_CELLS, dem_size
from fieldtool.project.keyspec import KeySpec, spec_of
from fieldtool.project.model import Project
from fieldtool.project.sections import parse as parse_sections

# bounds for what no declaration bounds
NUMBER_LIMIT = 1e12  # |x| of any number
INT_LIMIT = 10**9
LIST_LIMIT = 100_000  # items of any list
TEXT_LIMIT = 1000  # characters of a text value that is not a path
PATH_LIMIT = 4096  # characters of a path
PATH_PART_LIMIT = 255  # characters of one path component
NESTING_LIMIT = 4  # depth of lists/tables inside a filter table
BACKGROUND_MEMORY_LIMIT = 1_500_000_000  # bytes the median background filter may hold (samples x frame x 4 B x 3)
GCP_MIN_SEPARATION_PX = 2.0  # two GCP pixels closer than this are one point
COLLINEAR_RELATIVE = 0.01  # a point closer than this fraction of the longest side to the line of two others
COLLINEAR_MIN_PX = 1.5  # ... or closer than this many pixels, is on that line

_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_KEY = re.compile(r"^[a-z_][a-z0-9_]*(\[\d+\])?(\.[a-z_][a-z0-9_]*(\[\d+\])?)*$")


@dataclass(frozen=True)
class Problem:
    """One problem of one key. ``severity`` is "error" (the run is refused) or "warning"."""

    key: str
    message: str
    severity: str = "error"

    def __str__(self) -> str:
        return f"{self.key}: {self.message}"


# ---------------------------------------------------------------------------------------------
# public API


def validate(project, *, files: bool = True) -> list[Problem]:
    """Every problem of ``project`` (a ``fieldtool.project.model.Project``), in key order.

    Never raises: a check that cannot run is itself reported as a problem of its key.
    """
    v = _Validator(project, files)
    v.run()
    return v.problems


def problems_for(project, prefix: str, *, files: bool = True) -> list[Problem]:
    """The problems whose key starts with ``prefix`` ("ortho." for the ortho step, "filters")."""
    return [p for p in validate(project, files=files) if p.key.startswith(prefix)]


def check(project, *, files: bool = True, prefix: str = "") -> list[Problem]:
    """Raise ``ParameterError`` with the first error's message; return the warnings otherwise."""
    probs = problems_for(project, prefix, files=files) if prefix else validate(project, files=files)
    for p in probs:
        if p.severity == "error":
            raise ParameterError(str(p))
    return probs


def value_problems(project, keys: Iterable[str]) -> list[Problem]:
    """The problems of each value of ``keys`` by itself: type, unit range, finiteness, list shape (what a key's
    declaration says; no check across keys, nothing on disk). For a writer of single keys (the viewer's picks,
    ``calibrate --project``): a half-picked list of GCPs passes, a NaN in it does not."""
    v = _Validator(project, False)
    v.partial = True
    wanted = set(keys)
    hints = typing.get_type_hints(Project)
    for f in dataclasses.fields(Project):
        val = getattr(project, f.name, None)
        if dataclasses.is_dataclass(val):
            sub_hints = typing.get_type_hints(type(val))
            for sf in dataclasses.fields(val):
                k = f"{f.name}.{sf.name}"
                if k in wanted:
                    v.guarded(k, v.value, k, getattr(val, sf.name, None), sub_hints[sf.name], spec_of(sf))
        elif f.name in wanted:
            v.guarded(f.name, v.value, f.name, val, hints[f.name], spec_of(f))
    return v.problems


def path_problem(path: Path | str, key: str, *, kind: str = "file") -> str | None:
    """Why ``path`` cannot be read as ``kind`` ("file" or "video"), or None. Never opens the file
    (a FIFO named as a video must not block)."""
    text = str(path)
    msg = _path_text_problem(text)
    if msg:
        return msg
    p = Path(text)
    if kind == "video" and is_pattern(text):
        parent = Path(text).parent
        if not parent.is_dir():
            return f"{parent}: the folder of this pattern does not exist; give the image folder or the video file"
        if not literal_glob(text):
            return f"{text}: no file matches this pattern"
        return None
    try:
        st = os.stat(p)
    except FileNotFoundError:
        what = "video" if kind == "video" else "file"
        return f"{p}: {what} not found; check the name, or give the path relative to the project file"
    except NotADirectoryError:
        return f"{p}: a part of this path is a file, not a folder"
    except PermissionError:
        return f"{p}: permission denied; make it readable"
    except (OSError, ValueError) as e:
        return f"{p}: cannot be read ({getattr(e, 'strerror', None) or e})"
    if stat.S_ISDIR(st.st_mode):
        if kind == "video":
            return None if os.access(p, os.R_OK | os.X_OK) else f"{p}: permission denied on this folder"
        return f"{p}: is a folder; give a file"
    if not stat.S_ISREG(st.st_mode):
        what = "a pipe (FIFO)" if stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "a device"
        return f"{p}: is {what}, not a regular file; give a file saved on disk"
    if st.st_size == 0:
        return f"{p}: the file is empty"
    if not os.access(p, os.R_OK):
        return f"{p}: permission denied; make it readable"
    return None


# ---------------------------------------------------------------------------------------------
# helpers


def out_path_problem(text: str) -> str | None:
    """A file written into the output folder (path = "out", e.g. rerun.path) stays inside it: no absolute
    path, no ``~``, no ``..``, not the folder itself. (rerun_log.confined_rrd_path also resolves links.)"""
    p = Path(text)
    if not text:
        return None  # not given: the default name
    if text.strip() in (".", "..") or p.name in ("", ".", ".."):
        return f"{text!r} is not a file name; give one such as run.rrd (written in the output folder)"
    if p.is_absolute() or text.startswith("~") or ".." in p.parts:
        return f"{text!r} points outside the output folder; give a file name such as run.rrd"
    return None


def _path_text_problem(text: str) -> str | None:
    if _CONTROL.search(text):
        return f"{text[:60]!r}: contains a control character (newline, tab, ...); remove it"
    if len(text) > PATH_LIMIT:
        return f"the path has {len(text)} characters (at most {PATH_LIMIT}); give a shorter path"
    if any(len(part) > PATH_PART_LIMIT for part in text.split(os.sep)):
        return f"a name in this path is longer than {PATH_PART_LIMIT} characters; give a shorter path"
    return None


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return repr(x) if not math.isfinite(x) else f"{x:g}"
    s = repr(x)
    return s if len(s) <= 60 else s[:57] + "..."


def _unwrap(tp: Any) -> tuple[Any, bool]:
    """(type without None, optional?)"""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return (args[0] if len(args) == 1 else Any), True
    return tp, False


def _depth(v: Any, limit: int) -> int:
    """Nesting depth of lists/dicts in ``v`` (stops counting past ``limit``)."""
    stack = [(v, 0)]
    deepest = 0
    while stack:
        x, d = stack.pop()
        deepest = max(deepest, d)
        if deepest > limit:
            return deepest
        if isinstance(x, list):
            stack.extend((y, d + 1) for y in x)
        elif isinstance(x, dict):
            stack.extend((y, d + 1) for y in x.values())
    return deepest


def _seg_dist(p, a, b) -> float:
    """Distance of point p from the infinite line through a and b."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    n = math.hypot(dx, dy)
    if n == 0:
        return math.hypot(p[0] - a[0], p[1] - a[1])
    return abs(dx * (p[1] - a[1]) - dy * (p[0] - a[0])) / n


def coincident_pairs(pts: list, tol: float) -> list[tuple[int, int]]:
    """Index pairs of points (2-D, first two coordinates) closer than ``tol``."""
    out = []
    for i in range(len(pts)):
        for j in range(i + 1, len(pts)):
            if math.hypot(pts[i][0] - pts[j][0], pts[i][1] - pts[j][1]) < tol:
                out.append((i, j))
    return out


def collinear_triples(pts: list, rel: float = COLLINEAR_RELATIVE, min_abs: float = 0.0) -> list[tuple[int, int, int]]:
    """Triples of points (2-D) of which one lies on the line of the other two (within ``rel`` of
    the triangle's longest side, or ``min_abs``)."""
    out = []
    n = len(pts)
    for i in range(n):
        for j in range(i + 1, n):
            for k in range(j + 1, n):
                a, b, c = pts[i], pts[j], pts[k]
                sides = [(a, b, c), (b, c, a), (a, c, b)]
                longest = max(math.hypot(p[0] - q[0], p[1] - q[1]) for p, q, _ in sides)
                p, q, r = max(sides, key=lambda s: math.hypot(s[0][0] - s[1][0], s[0][1] - s[1][1]))
                if _seg_dist(r, p, q) <= max(rel * longest, min_abs):
                    out.append((i, j, k))
    return out


def _rects_intersect_segment(rect, a, b) -> bool:
    """Does the segment a-b cross the rectangle [x0, y0, x1, y1]?"""
    x0, x1 = sorted((rect[0], rect[2]))
    y0, y1 = sorted((rect[1], rect[3]))
    # Liang-Barsky clipping
    t0, t1 = 0.0, 1.0
    dx, dy = b[0] - a[0], b[1] - a[1]
    for p, q in ((-dx, a[0] - x0), (dx, x1 - a[0]), (-dy, a[1] - y0), (dy, y1 - a[1])):
        if p == 0:
            if q < 0:
                return False
            continue
        t = q / p
        if p < 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return False
    return True


_probe_cache: dict[tuple, tuple[int, int] | str] = {}


def frame_size(path: Path, key: str = "video.path") -> tuple[int, int] | str:
    """(width, height) of a clip from its header (cached on path, size and mtime), or a message."""
    try:
        st = os.stat(path)
        ck: tuple[str, int | None, int | None] = (str(path), st.st_size, st.st_mtime_ns)
    except OSError:
        ck = (str(path), None, None)
    if ck in _probe_cache:
        return _probe_cache[ck]
    try:
        src = FrameSource(path, 0.0, None, 1, 1.0)
        h, w = src.shape
        res: tuple[int, int] | str = (int(w), int(h))
    except FieldToolError as e:
        res = str(e)
    except Exception as e:  # noqa: BLE001 - a decoder failure is a property of the file
        res = f"{path}: cannot be read as a video ({type(e).__name__}: {e})"
    if len(_probe_cache) > 64:
        _probe_cache.clear()
    _probe_cache[ck] = res
    return res


_clip_cache: dict[tuple, str | None] = {}


def clip_problem(
    path: Path, start_s: float, end_s: float | None, step: int, interval: float | None, capture_fps: float | None
) -> str | None:
    """Why the clip cannot be read over this range ("key: message"), or None; cached on the file's
    size and mtime, so that the TUI may ask on every keystroke."""
    try:
        st = os.stat(path)
        ck = (str(path), st.st_size, st.st_mtime_ns, start_s, end_s, step, interval, capture_fps)
    except OSError:
        ck = None
    if ck is not None and ck in _clip_cache:
        return _clip_cache[ck]
    try:
        FrameSource(path, start_s, end_s, step, interval, capture_fps)
        res = None
    except FieldToolError as e:
        res = str(e)
    except Exception as e:  # noqa: BLE001 - a decoder failure is a property of the file
        res = f"{path}: cannot be read as a video ({type(e).__name__}: {e})"
    if ck is not None:
        if len(_clip_cache) > 256:
            _clip_cache.clear()
        _clip_cache[ck] = res
    return res


# ---------------------------------------------------------------------------------------------
# the validator


class _Validator:
    def __init__(self, project, files: bool):
        self.p = project
        self.files = files
        self.problems: list[Problem] = []
        self.bad: set[str] = set()
        self.checked: set[str] = set()  # path keys whose file was checked
        self.partial = False  # a writer of single keys: a point list still being picked passes its count check

    def err(self, key: str, msg: str) -> None:
        self.bad.add(key)
        self.problems.append(Problem(key, msg, "error"))

    def warn(self, key: str, msg: str) -> None:
        self.problems.append(Problem(key, msg, "warning"))

    def ok(self, *keys: str) -> bool:
        """No error yet on any of ``keys`` (nor on items of them)."""
        return not any(b == k or b.startswith(k + "[") or b.startswith(k + ".") for k in keys for b in self.bad)

    def from_error(self, e: Exception, default_key: str) -> None:
        """A FieldToolError message "key: text" as a problem of that key."""
        text = str(e)
        head, _, rest = text.partition(": ")
        if rest and _KEY.match(head):
            self.err(head, rest)
        else:
            self.err(default_key, text)

    def guarded(self, key: str, fn, *args) -> None:
        try:
            fn(*args)
        except FieldToolError as e:
            self.from_error(e, key)
        except Exception as e:  # noqa: BLE001 - validation must never crash its caller
            self.err(key, f"could not be checked ({type(e).__name__}: {e}); check the value's type and shape")

    # -- driver ---------------------------------------------------------------------------------
    def run(self) -> None:
        p = self.p

        hints = typing.get_type_hints(Project)
        for f in dataclasses.fields(Project):
            if not f.metadata.get("saved", True):
                continue
            val = getattr(p, f.name, None)
            if dataclasses.is_dataclass(val):
                sub_hints = typing.get_type_hints(type(val))
                for sf in dataclasses.fields(val):
                    k = f"{f.name}.{sf.name}"
                    self.guarded(k, self.value, k, getattr(val, sf.name, None), sub_hints[sf.name], spec_of(sf))
            else:
                self.guarded(f.name, self.value, f.name, val, hints[f.name], spec_of(f))
        for name, fn in (
            ("video", self.video),
            ("cross_section", self.cross_section),
            ("filters", self.filters),
            ("stabilize", self.stabilize),
            ("ortho", self.ortho),
            ("water_level", self.water_level),
            ("roi", self.roi),
            ("piv", self.piv),
            ("section", self.section),
            ("calibration", self.calibration),
            ("sections", self.sections),
            ("overlay", self.overlay),
        ):
            self.guarded(name, fn)
        if self.files:
            self.guarded("paths", self.unused_paths)
        order = {k: i for i, k in enumerate(_key_order())}
        self.problems.sort(
            key=lambda pr: (order.get(pr.key.split("[")[0], len(order)), order.get(pr.key.split(".")[0], len(order)))
        )

    # -- one value, from its declaration and annotation ------------------------------------------
    def value(self, k: str, v: Any, tp: Any, spec: KeySpec | None) -> None:
        spec = spec or KeySpec()
        tp, optional = _unwrap(tp)
        if v is None:
            if not optional:
                self.err(k, "is missing; give a value")
            return
        origin = typing.get_origin(tp)
        if tp is bool:
            if not isinstance(v, bool):
                self.err(k, f"expected true or false, got {_fmt(v)}")
        elif tp in (int, float):
            self.number(k, v, tp, spec)
        elif tp is str:
            self.text(k, v, spec)
        elif origin is list:
            self.list_(k, v, tp, spec)
        elif origin is dict or tp is dict:
            if not isinstance(v, dict):
                self.err(k, f"expected a table, got {_fmt(v)}")
            elif _depth(v, NESTING_LIMIT) > NESTING_LIMIT:
                self.err(k, f"nested more than {NESTING_LIMIT} levels deep; give plain values")
        elif tp is Any:
            if _depth(v, NESTING_LIMIT) > NESTING_LIMIT:
                self.err(k, f"nested more than {NESTING_LIMIT} levels deep; give plain values")

    def number(self, k: str, v: Any, tp: Any, spec: KeySpec) -> bool:
        unit = f" {spec.unit}" if spec.unit else ""
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.err(k, f"expected {'a whole number' if tp is int else 'a number'}, got {_fmt(v)}")
            return False
        if tp is int and not isinstance(v, int):
            self.err(k, f"expected a whole number, got {_fmt(v)}")
            return False
        if isinstance(v, float) and not math.isfinite(v):
            self.err(k, f"{_fmt(v)} is not a finite number; give a value in{unit or ' its unit'}")
            return False
        lo = spec.gt if spec.gt is not None else spec.ge
        hi = spec.lt if spec.lt is not None else spec.le
        rng = _range_text(spec)
        if (
            spec.gt is not None
            and not v > spec.gt
            or spec.ge is not None
            and not v >= spec.ge
            or spec.lt is not None
            and not v < spec.lt
            or spec.le is not None
            and not v <= spec.le
        ):
            self.err(k, f"{_fmt(v)}{unit} is out of range; give a value {rng}{unit}")
            return False
        limit = INT_LIMIT if tp is int else NUMBER_LIMIT
        if lo is None and hi is None and abs(v) > limit:
            self.err(k, f"{_fmt(v)} is too large (at most {limit:g} in magnitude)")
            return False
        return True

    def text(self, k: str, v: Any, spec: KeySpec) -> None:
        if not isinstance(v, str):
            self.err(k, f"expected text in quotes, got {_fmt(v)}")
            return
        if spec.choices is not None:
            if v not in spec.choices:
                self.err(k, f"{v[:60]!r} is not allowed; use one of {', '.join(repr(c) for c in spec.choices)}")
            return
        if spec.path is not None:
            msg = _path_text_problem(v) or (out_path_problem(v) if spec.path == "out" else None)
            if msg:
                self.err(k, msg)
            elif spec.path == "out" and (not v.strip() or v.endswith(("/", os.sep)) or Path(v).name in ("", ".", "..")):
                self.err(k, f'{v!r} is not a file name; give one like "run.rrd"')
            elif spec.path == "out" and os.path.isabs(v) and os.path.exists(v) and not os.path.isfile(v):
                self.err(k, f"{v}: exists and is not a regular file (a folder, pipe or device); give a file name")
            return
        limit = spec.max_items or TEXT_LIMIT
        if len(v) > limit:
            self.err(k, f"{len(v)} characters is too long (at most {limit})")
        elif _CONTROL.search(v):
            self.err(k, f"{v[:60]!r} contains a control character (newline, tab, ...); remove it")

    def list_(self, k: str, v: Any, tp: Any, spec: KeySpec) -> None:
        if not isinstance(v, list):
            self.err(k, f"expected a list, got {_fmt(v)}")
            return
        limit = spec.max_items or LIST_LIMIT
        if len(v) > limit:
            self.err(k, f"{len(v)} items is too many (at most {limit})")
            return
        half_picked = self.partial and spec.counts is not None and len(v) < max(spec.counts)
        if spec.counts is not None and len(v) not in spec.counts and not half_picked:
            self.err(k, f"has {len(v)} items; give {' or '.join(str(c) for c in spec.counts)}")
            return
        (item_tp,) = typing.get_args(tp) or (Any,)
        item_tp, _ = _unwrap(item_tp)
        if typing.get_origin(item_tp) is list:  # a list of lists: points, rectangles, polygons
            self.nested(k, v, item_tp, spec)
            return
        item_spec = dataclasses.replace(spec, counts=None, max_items=None)
        for i, x in enumerate(v):
            self.value(f"{k}[{i}]", x, item_tp, item_spec)

    def nested(self, k: str, v: list, item_tp: Any, spec: KeySpec) -> None:
        (leaf_tp,) = typing.get_args(item_tp) or (Any,)
        leaf_tp, _ = _unwrap(leaf_tp)
        item_spec = dataclasses.replace(spec, counts=None, max_items=None)
        if typing.get_origin(leaf_tp) is list:  # list of polygons
            for i, poly in enumerate(v):
                if not isinstance(poly, list):
                    self.err(f"{k}[{i}]", f"expected a list of points, got {_fmt(poly)}")
                    continue
                self.list_(f"{k}[{i}]", poly, item_tp, dataclasses.replace(spec, counts=None))
            return
        dims = spec.dim if isinstance(spec.dim, tuple) else (spec.dim,) if spec.dim else None
        lengths = set()
        for i, pt in enumerate(v):
            if not isinstance(pt, list):
                self.err(f"{k}[{i}]", f"expected a list like [x, y], got {_fmt(pt)}")
                return
            lengths.add(len(pt))
            if dims is not None and len(pt) not in dims:
                want = " or ".join(str(d) for d in dims)
                self.err(
                    k,
                    f"item {i + 1} has {len(pt)} numbers; every item needs {want} (e.g. "
                    f"{'[x, y]' if dims == (2,) else '[x0, y0, x1, y1]' if dims == (4,) else '[X, Y] or [X, Y, Z]'})",
                )
                return
            for j, x in enumerate(pt):
                if not self.number(f"{k}[{i}][{j}]", x, leaf_tp if leaf_tp in (int, float) else float, item_spec):
                    return
        if len(lengths) > 1:
            self.err(
                k,
                f"the items have different lengths ({', '.join(map(str, sorted(lengths)))}); give the same "
                "number of coordinates in every item",
            )

    # -- cross-key and geometry checks ------------------------------------------------------------
    def file(self, k: str, rel: str, kind: str = "file", *, required: bool = True) -> bool:
        if not rel:
            if required:
                self.err(k, "no file given; set the path")
            return False
        self.checked.add(k)
        if not self.files or not self.ok(k):
            return self.ok(k)
        msg = path_problem(self.p.resolve(rel), k, kind=kind)
        if msg:
            (self.err if required else self.warn)(k, msg)
            return False
        return True

    def unused_paths(self) -> None:
        """Paths the current methods do not read: a pipe, a device or a folder is still an error
        (something would open it later); a missing file is a warning."""
        for k, spec in describe().items():
            if spec is None or spec.path not in ("file", "video") or k in self.checked or not self.ok(k):
                continue
            table, _, name = k.rpartition(".")
            rel = getattr(getattr(self.p, table) if table else self.p, name, "")
            if not rel or not isinstance(rel, str):
                continue
            msg = path_problem(self.p.resolve(rel), k, kind=spec.path)
            if msg:
                (self.warn if "not found" in msg else self.err)(k, msg)

    def video(self) -> None:
        v = self.p.video
        if self.ok("video.start_s", "video.end_s") and v.end_s is not None and v.end_s <= v.start_s:
            self.err("video.end_s", f"{v.end_s:g} s must be after video.start_s ({v.start_s:g} s)")
        if self.file("video.path", v.path, "video") and self.ok(
            "video.start_s", "video.end_s", "video.step", "video.frame_interval_s", "video.capture_fps"
        ):
            msg = clip_problem(self.p.resolve(v.path), v.start_s, v.end_s, v.step, v.frame_interval_s, v.capture_fps)
            if msg:
                self.from_error(ParameterError(msg), "video.path")

    def cross_section(self) -> None:
        c = self.p.cross_section
        if not self.ok("cross_section.shape"):
            return
        if c.shape == "":
            if self.file("cross_section.path", c.path) and self.files:
                msg = file_size_problem(self.p.resolve(c.path))  # a 50 MB file is refused at once
                if msg:
                    self.err("cross_section.path", msg)
            return
        if c.shape in ("rectangular", "trapezoidal", "parabolic"):
            for name in ("top_width_m", "depth_m"):
                if getattr(c, name) is None:
                    self.err(f"cross_section.{name}", f"a positive number is needed for a {c.shape} section")
            if (
                c.shape == "trapezoidal"
                and self.ok("cross_section.bottom_width_m", "cross_section.top_width_m")
                and c.bottom_width_m is not None
                and c.top_width_m is not None
                and c.bottom_width_m >= c.top_width_m
            ):
                self.err(
                    "cross_section.bottom_width_m",
                    f"{c.bottom_width_m:g} m must be less than top_width_m ({c.top_width_m:g} m)",
                )
        if c.shape == "free" and self.ok("cross_section.points") and len(c.points) < 3:
            self.err("cross_section.points", "a free shape needs at least 3 [station_m, elevation_m] points")
        if c.shape == "free" and self.ok("cross_section.points"):
            for i, pt in enumerate(c.points):  # the limit a cross-section file's rows have (processing.cross_section)
                if any(isinstance(v, (int, float)) and not abs(v) <= MAX_ABS_M for v in pt):
                    self.err(f"cross_section.points[{i}]", f"{_fmt(list(pt))}: beyond ±10 km; give metres")
                    break

    def calibration(self) -> None:
        c = self.p.calibration
        if c.path:
            self.file("calibration.path", c.path)

    def sections(self) -> None:
        """Several sections: each table's keys, its two points, and its cross-section file."""
        if not self.ok("sections") or not isinstance(self.p.sections, list):
            return
        try:
            specs = parse_sections(self.p)
        except FieldToolError as e:
            self.from_error(e, "sections")
            return
        for sp in specs:
            if sp.cross_section:
                self.file(f"sections[{sp.index}].cross_section", sp.cross_section)

    def filters(self) -> None:
        fl = self.p.filters
        if not self.ok("filters") or not isinstance(fl, list):
            return
        for i, item in enumerate(fl):
            if _depth(item, NESTING_LIMIT) > NESTING_LIMIT:
                self.err(f"filters[{i}]", f"nested more than {NESTING_LIMIT} levels deep; give plain values")
                return

        try:
            FilterStack.from_config(fl)
        except FieldToolError as e:
            self.from_error(e, "filters")
            return
        for i, item in enumerate(fl):
            if isinstance(item, dict) and item.get("name") == "background" and item.get("method", "median") == "median":
                self.background_memory(i, item)

    def background_memory(self, i: int, item: dict) -> None:
        samples = item.get("samples")
        if samples is None:
            samples = next((p.default for p in FILTERS["background"].params if p.name == "samples"), 25)
        if not self.files or not self.p.video.path or not self.ok("video.path"):
            return
        size = frame_size(self.p.resolve(self.p.video.path))
        if isinstance(size, str):
            return
        w, h = size
        need = 3 * (int(samples) + 1) * w * h * 4
        if need > BACKGROUND_MEMORY_LIMIT:
            most = max(3, BACKGROUND_MEMORY_LIMIT // (3 * w * h * 4) - 1)
            self.err(
                f"filters[{i}].samples",
                f"{samples} samples of {w}x{h} frames need {need / 2**30:.1f} GiB for "
                f'the median; use at most {most} (or method = "mean")',
            )

    def stabilize(self) -> None:
        s = self.p.stabilize
        if not self.ok("stabilize.regions_px"):
            return
        for i, r in enumerate(s.regions_px):
            if abs(r[2] - r[0]) < 8 or abs(r[3] - r[1]) < 8:
                self.err(
                    f"stabilize.regions_px[{i}]", f"{r} is not a rectangle of at least 8x8 px; give [x0, y0, x1, y1]"
                )
        if not s.enabled:
            return
        if self.ok("stabilize.water_polygon_px") and s.water_polygon_px and len(s.water_polygon_px) < 3:
            self.err("stabilize.water_polygon_px", "a polygon needs at least 3 points")
        sec = self.p.section.points_px
        if self.ok("section.points_px") and len(sec) == 2:
            for i, r in enumerate(s.regions_px):
                if _rects_intersect_segment(r, sec[0], sec[1]):
                    self.err(
                        f"stabilize.regions_px[{i}]",
                        "this rectangle lies across the section of interest, on "
                        "the water; stable regions must cover fixed ground (banks)",
                    )

    def ortho(self) -> None:
        o = self.p.ortho
        if not self.ok("ortho.method", "ortho.gcp_px", "ortho.gcp_world_m", "ortho.distances_m"):
            return
        px = o.gcp_px
        if o.method == "none":
            return
        if o.method == "two_points":
            if len(px) != 2:
                self.err(
                    "ortho.gcp_px", f"has {len(px)} points; method = two_points needs exactly 2 [x, y] points P1, P2"
                )
            if len(o.distances_m) != 1:
                self.err(
                    "ortho.distances_m",
                    f"has {len(o.distances_m)} values; method = two_points needs [|P1P2|] in metres",
                )
            if self.ok("ortho.gcp_px") and len(px) == 2 and coincident_pairs(px, GCP_MIN_SEPARATION_PX):
                self.err("ortho.gcp_px", "P1 and P2 are the same point; pick two GCPs far apart")
            return
        need = {"distances": 4, "world": 4, "pose": 6}.get(o.method, 4)
        if o.method == "distances":
            if len(px) != 4:
                self.err(
                    "ortho.gcp_px", f"has {len(px)} points; method = distances needs exactly 4 [x, y] points P1..P4"
                )
            if len(o.distances_m) != 6:
                self.err("ortho.distances_m", f"has {len(o.distances_m)} values; give the 6 distances L1..L6 in metres")
        else:
            if len(px) < need:
                self.err("ortho.gcp_px", f"has {len(px)} points; method = {o.method} needs at least {need}")
            if len(o.gcp_world_m) != len(px):
                self.err(
                    "ortho.gcp_world_m",
                    f"has {len(o.gcp_world_m)} points but ortho.gcp_px has {len(px)}; give one "
                    "world point per pixel point",
                )
            elif o.method == "pose" and any(len(w) != 3 for w in o.gcp_world_m):
                self.err("ortho.gcp_world_m", "method = pose needs [X, Y, Z] for every GCP")
        if not self.ok("ortho.gcp_px"):
            return
        pairs = coincident_pairs(px, GCP_MIN_SEPARATION_PX)
        if pairs:
            i, j = pairs[0]
            self.err(
                "ortho.gcp_px",
                f"P{i + 1} and P{j + 1} are the same point ({_fmt(px[i])}, {_fmt(px[j])}); "
                "pick each GCP on its own target",
            )
            return
        if len(px) == 4 or (o.method == "world" and len(px) >= 3):
            tri = collinear_triples(px, COLLINEAR_RELATIVE, COLLINEAR_MIN_PX)
            if len(px) == 4 and tri or len(px) > 4 and len(tri) == math.comb(len(px), 3):
                i, j, k = tri[0]
                self.err(
                    "ortho.gcp_px",
                    f"P{i + 1}, P{j + 1} and P{k + 1} lie on one line in the image; the mapping "
                    "needs the GCPs spread over both banks (re-pick them)",
                )
                return
        if o.method in ("world", "pose") and self.ok("ortho.gcp_world_m") and len(o.gcp_world_m) >= 3:
            w = o.gcp_world_m
            extent = max(max(abs(a[0] - b[0]), abs(a[1] - b[1])) for a in w for b in w) or 1.0
            pairs = coincident_pairs(w, 1e-3 * extent if extent else 1e-6)
            if pairs:
                i, j = pairs[0]
                self.err(
                    "ortho.gcp_world_m", f"P{i + 1} and P{j + 1} have the same X, Y; give each GCP its own coordinates"
                )
                return
            tri = collinear_triples(w, COLLINEAR_RELATIVE)
            if (len(w) == 4 and tri and o.method == "world") or len(tri) == math.comb(len(w), 3):
                i, j, k = tri[0]
                self.err(
                    "ortho.gcp_world_m",
                    f"P{i + 1}, P{j + 1} and P{k + 1} lie on one line; the GCPs must span an area on both banks",
                )

    def water_level(self) -> None:
        w = self.p.water_level
        m = w.method
        if not self.ok("water_level.method"):
            return
        req = {
            "value": ("value_m",),
            "width": ("width_m",),
            "dem": ("dem_precision_mm",),
            "angle_height": ("dh_m",),
            "image": (),
        }.get(m, ())
        for name in req:
            if getattr(w, name) is None:
                self.err(f"water_level.{name}", f"is needed for water_level.method = {m}; give it")
        if m == "dem":
            for name in ("dem_x_m", "dem_y_m"):
                val = getattr(w, name)
                if self.ok(f"water_level.{name}") and (len(val) != 2 or not val[0] < val[1]):
                    self.err(f"water_level.{name}", f"{_fmt(val)}: give [min, max] with min < max, in metres")
            if (
                self.ok("water_level.dem_y_m", "water_level.dem_section_y_m")
                and w.dem_section_y_m is not None
                and len(w.dem_y_m) == 2
                and not w.dem_y_m[0] <= w.dem_section_y_m <= w.dem_y_m[1]
            ):
                self.err(
                    "water_level.dem_section_y_m",
                    f"{w.dem_section_y_m:g} m is outside the DEM's y range "
                    f"{w.dem_y_m}; give a y inside it (or leave it out)",
                )
            if self.file("water_level.dem_path", w.dem_path):
                self.dem_header()
        if m == "angle_height":
            self.file("water_level.image1", w.image1)
            self.file("water_level.image2", w.image2)
            for name in ("edges1_px", "edges2_px"):
                if self.ok(f"water_level.{name}") and len(getattr(w, name)) != 2:
                    self.err(f"water_level.{name}", "give the left and right water edges [[x, y], [x, y]]")
        if m == "image":
            if self.ok("water_level.edges_px") and len(w.edges_px) != 2:
                self.err("water_level.edges_px", "give the left and right water edges [[x, y], [x, y]]")
            if self.p.ortho.method == "none":
                self.err(
                    "water_level.method",
                    "the image method measures the level on the ortho mapping; ortho.method = none has none",
                )
        for name in ("edges_px", "edges1_px", "edges2_px"):
            pts = getattr(w, name)
            if self.ok(f"water_level.{name}") and len(pts) == 2 and coincident_pairs(pts, 1.0):
                self.err(
                    f"water_level.{name}", "the two water edges are the same point; pick the left and the right edge"
                )

    def dem_header(self) -> None:
        """The DEM's size from its header (GDAL), before anything reads its cells."""
        path = self.p.resolve(self.p.water_level.dem_path)
        try:
            w, h = dem_size(path)
        except Exception as e:  # noqa: BLE001 - any failure: not a readable raster
            self.err(
                "water_level.dem_path",
                f"{path}: cannot read this DEM as a raster ({type(e).__name__}); export it as a GeoTIFF of elevations",
            )
            return
        if w * h > MAX_DEM_CELLS:
            self.err(
                "water_level.dem_path",
                f"{path}: the DEM header says {w}x{h} cells (more than "
                f"{MAX_DEM_CELLS:,}); crop it to the bank near the section",
            )

    def roi(self) -> None:
        r = self.p.roi.rect_px
        if self.ok("roi.rect_px") and len(r) == 4 and (abs(r[2] - r[0]) < 8 or abs(r[3] - r[1]) < 8):
            self.err(
                "roi.rect_px",
                f"{[_fmt(x) for x in r]} encloses no usable area; give two opposite corners "
                "[x0, y0, x1, y1] at least 8 px apart",
            )
        if self.ok("roi.masks_px"):
            for i, poly in enumerate(self.p.roi.masks_px):
                if len(poly) < 3:
                    self.err(f"roi.masks_px[{i}]", f"has {len(poly)} points; a polygon needs at least 3")

    def piv(self) -> None:
        v = self.p.piv
        if self.ok("piv.window_px", "piv.overlap_px") and v.overlap_px >= v.window_px:
            self.err(
                "piv.overlap_px",
                f"{v.overlap_px} px must be less than piv.window_px ({v.window_px} px); "
                f"half the window ({v.window_px // 2}) is usual",
            )
        if self.ok("piv.window_px", "piv.search_px") and v.search_px is not None:
            if v.search_px < v.window_px:
                self.err("piv.search_px", f"{v.search_px} px must be at least piv.window_px ({v.window_px} px)")
            elif v.search_px > 8 * v.window_px:
                self.err(
                    "piv.search_px",
                    f"{v.search_px} px is more than 8 windows ({8 * v.window_px} px); use a "
                    "larger window_px or a smaller search area",
                )

    def overlay(self) -> None:
        o = self.p.overlay
        if self.ok("overlay.width_px") and 0 < o.width_px < 160:
            self.err(
                "overlay.width_px",
                f"{o.width_px} px leaves no room for the legend and the text; give 160 px "
                "or more (960 is usual), or 0 for the clip's own width",
            )

    def section(self) -> None:
        s = self.p.section
        if self.ok("section.points_px") and len(s.points_px) == 2 and coincident_pairs(s.points_px, 1.0):
            self.err("section.points_px", "the two end points are the same; pick the left then the right water edge")


def _range_text(spec: KeySpec) -> str:
    lo = f"> {spec.gt:g}" if spec.gt is not None else f">= {spec.ge:g}" if spec.ge is not None else ""
    hi = f"< {spec.lt:g}" if spec.lt is not None else f"<= {spec.le:g}" if spec.le is not None else ""
    return " and ".join(t for t in (lo, hi) if t) or "in range"


def _key_order() -> list[str]:
    out = []
    proj = Project()
    for f in dataclasses.fields(Project):
        val = getattr(proj, f.name)
        out.append(f.name)
        if dataclasses.is_dataclass(val):
            out += [f"{f.name}.{sf.name}" for sf in dataclasses.fields(val)]
    return out


def describe(keys: Iterable[str] | None = None) -> dict[str, KeySpec | None]:
    """Declarations of the project's keys ("video.start_s" -> KeySpec or None if undeclared)."""
    out: dict[str, KeySpec | None] = {}
    proj = Project()
    for f in dataclasses.fields(Project):
        if not f.metadata.get("saved", True):
            continue
        val = getattr(proj, f.name)
        if dataclasses.is_dataclass(val):
            for sf in dataclasses.fields(val):
                out[f"{f.name}.{sf.name}"] = spec_of(sf)
        else:
            out[f.name] = spec_of(f)
    return out if keys is None else {k: out.get(k) for k in keys}
