"""Every parameter the TUI edits: project key, label, unit, default, validator and help line.

A ``Field`` turns the text in an input into the project value (or a message saying what is
wrong and how to fix it) and back. Keys are the project's own (``video.start_s``); a key ending in
``[i]`` is item ``i`` of a list (``ortho.gcp_px[0]`` is P1). Validation has two layers:

* ``parse`` : the text alone (a number, "x, y", ...), done as the user types;
* ``check`` : the value against the rest of the project (end after start, overlap < window ...),
  done as the user types and again before "next".
"""

from __future__ import annotations

import math
import re
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from fieldtool.project.model import Project

_INDEX = re.compile(r"^(.*)\[(\d+)\]$")
_SEP = re.compile(r"\s*[,\s]\s*")


class Invalid(ValueError):
    """Text that does not parse, or a value that does not pass its check; ``str`` is the message."""


# ---------------------------------------------------------------------------------------------
# formatting and parsing of values


def fmt_num(v: float | int | None) -> str:
    """Shortest text that reads back to the same number ("" for None)."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if math.isfinite(v) and float(v).is_integer() and abs(v) < 1e15:
        return str(int(v))
    return repr(float(v))


def fmt_px(v: float) -> str:
    """A pixel coordinate with at most 2 decimals (a click is no finer; a snapped centre keeps its digits in the
    file, the field shows it rounded)."""
    v = float(v)
    if not math.isfinite(v):
        return fmt_num(v)
    return fmt_num(round(v, 2))


def fmt_point(p, px: bool = False) -> str:
    return ", ".join(fmt_px(c) if px else fmt_num(float(c)) for c in p)


def fmt_points(pts, px: bool = False) -> str:
    return "; ".join(fmt_point(p, px) for p in pts)


def fmt_polygons(polys, px: bool = False) -> str:
    return " | ".join(fmt_points(p, px) for p in polys)


_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+$")
_HAS_DECIMAL_COMMA = re.compile(r"\d,\d")
DECIMAL_HINT = "use a decimal point (2.5, not 2,5) and ', ' or '; ' between numbers"


def _number(text: str, what: str) -> float:
    """A finite number; a single decimal comma ("2,5") is read as a decimal point."""
    if _DECIMAL_COMMA.match(text):
        text = text.replace(",", ".")
    try:
        v = float(text)
    except ValueError:
        raise Invalid(f"{text!r} is not a number{what}") from None
    if not math.isfinite(v):
        raise Invalid(f"{text!r} is not a finite number{what}")
    return v


def parse_floats(text: str, n: int | None = None, what: str = "numbers") -> list[float]:
    parts = [p for p in _SEP.split(text.strip()) if p]
    vals = [_number(p, "") for p in parts]
    if n is not None and len(vals) != n:
        hint = f"; {DECIMAL_HINT}" if _HAS_DECIMAL_COMMA.search(text) else ""
        raise Invalid(f"give {n} {what} separated by commas, got {len(vals)}{hint}")
    return vals


def parse_point(text: str) -> list[float]:
    """ "x, y" (comma, space or semicolon separated) -> [x, y]."""
    return parse_floats(text.replace(";", ","), 2, "numbers: x, y")


def parse_points(text: str, dim: int = 2) -> list[list[float]]:
    """ "x, y; x, y; ..." -> [[x, y], ...] (``dim`` numbers per point)."""
    pts = []
    for i, chunk in enumerate(c for c in text.split(";") if c.strip()):
        try:
            pts.append(parse_floats(chunk, dim, "numbers" if dim != 2 else "numbers: x, y"))
        except Invalid as e:
            raise Invalid(f"point {i + 1}: {e}") from None
    return pts


def parse_polygons(text: str) -> list[list[list[float]]]:
    """ "x, y; x, y; x, y | x, y; ..." -> polygons of at least 3 points."""
    polys = []
    for i, chunk in enumerate(c for c in text.split("|") if c.strip()):
        pts = parse_points(chunk)
        if len(pts) < 3:
            raise Invalid(f"mask {i + 1}: a polygon needs at least 3 points 'x, y; x, y; x, y'")
        polys.append(pts)
    return polys


# ---------------------------------------------------------------------------------------------
# the Field


Check = Callable[[Any, Project], "str | None"]


@dataclass(frozen=True)
class Field:
    """One parameter on a screen.

    kind: float | int | text | path | choice | point | points | polygons | floats
    required: True/False, or a predicate of the project.
    show: predicate of the project; hidden fields are neither shown nor checked.
    """

    key: str
    label: str
    unit: str
    kind: str
    help: str
    required: bool | Callable[[Project], bool] = False
    choices: tuple[tuple[str, Any], ...] = ()
    count: int | None = None  # floats/points: exact number of items
    check: Check | None = None
    show: Callable[[Project], bool] | None = None
    placeholder: str | Callable[[Project], str] = ""
    pickable: bool = False  # receives clicks from the viewer

    # -- project access --------------------------------------------------------------------
    def _split(self) -> tuple[list[str], int | None]:
        m = _INDEX.match(self.key)
        if m:
            return m.group(1).split("."), int(m.group(2))
        return self.key.split("."), None

    def get(self, project: Project) -> Any:
        parts, idx = self._split()
        obj: Any = project
        for p in parts:
            obj = getattr(obj, p)
        if idx is not None:
            return obj[idx] if idx < len(obj) else None
        return obj

    def set(self, project: Project, value: Any) -> None:
        parts, idx = self._split()
        obj: Any = project
        for p in parts[:-1]:
            obj = getattr(obj, p)
        if idx is None:
            setattr(obj, parts[-1], value)
            return
        lst = list(getattr(obj, parts[-1]))
        if value is None:
            del lst[idx:]
        elif idx < len(lst):
            lst[idx] = value
        else:
            lst.append(value)
        setattr(obj, parts[-1], lst)

    def nullable(self) -> bool:
        """Whether the key may be unset (its type allows None): an empty input unsets it."""
        parts, idx = self._split()
        if idx is not None:
            return False
        obj: Any = Project()
        for p in parts[:-1]:
            obj = getattr(obj, p)
        hint = typing.get_type_hints(type(obj))[parts[-1]]
        return type(None) in typing.get_args(hint)

    def default(self) -> Any:
        parts, idx = self._split()
        obj: Any = Project()
        for p in parts:
            obj = getattr(obj, p)
        return None if idx is not None else obj

    # -- text <-> value ----------------------------------------------------------------------
    def format(self, value: Any) -> str:
        if value is None:
            return ""
        k = self.kind
        if k in ("float", "int"):
            return fmt_num(value)
        px = self.unit == "px"
        if k == "point":
            return fmt_point(value, px)
        if k in ("points", "rects", "worldpoints"):
            return fmt_points(value, px)
        if k == "polygons":
            return fmt_polygons(value, px)
        if k == "floats":
            return ", ".join(fmt_num(float(v)) for v in value)
        return str(value)

    def parse(self, text: str) -> Any:
        """Value for ``text`` (None when empty and the key may be unset). Raises Invalid."""
        t = text.strip()
        k = self.kind
        if k in ("text", "path"):
            return t
        if not t:
            if k in ("points", "rects", "worldpoints", "polygons", "floats"):
                return []
            if not self.nullable():
                raise Invalid(
                    "a value is needed"
                    + (f" (default {self.format(self.default())})" if self.default() is not None else "")
                )
            return None
        if k == "float":
            return _number(t, "")
        if k == "int":
            try:
                return int(t)
            except ValueError:
                hint = f"; {DECIMAL_HINT}" if _HAS_DECIMAL_COMMA.search(t) else ""
                raise Invalid(f"{t!r} is not a whole number{hint}") from None
        if k == "point":
            return parse_point(t)
        if k == "points":
            pts = parse_points(t)
            if self.count is not None and len(pts) != self.count:
                raise Invalid(f"give {self.count} points 'x, y; x, y', got {len(pts)}")
            return pts
        if k == "rects":
            return parse_points(t, 4)
        if k == "worldpoints":
            pts = []
            for i, chunk in enumerate(c for c in t.split(";") if c.strip()):
                vals = parse_floats(chunk)
                if len(vals) not in (2, 3):
                    raise Invalid(f"point {i + 1}: give 'X, Y' or 'X, Y, Z', got {len(vals)} numbers")
                pts.append(vals)
            return pts
        if k == "polygons":
            return parse_polygons(t)
        if k == "floats":
            return parse_floats(t, self.count)
        raise Invalid(f"unsupported kind {k}")

    # -- checks ------------------------------------------------------------------------------
    def is_required(self, project: Project) -> bool:
        return self.required(project) if callable(self.required) else bool(self.required)

    def visible(self, project: Project) -> bool:
        return self.show is None or self.show(project)

    def validate(self, value: Any, project: Project) -> str | None:
        """Message if ``value`` is not acceptable for this key in ``project``, else None."""
        empty = value is None or value == "" or value == []
        if empty:
            if self.is_required(project):
                return f"{self.key}: required — {self.help}"
            return None
        if self.kind == "choice" and value not in [c[1] for c in self.choices]:
            return f"{self.key}: {value!r} is not one of {', '.join(str(c[1]) for c in self.choices)}"
        parts, idx = self._split()
        if idx is not None:
            have = self.get_list_len(project)
            if idx > have:
                return f"{self.key}: enter item {have + 1} first (items are kept in order)"
        if self.kind == "path" and value:
            p = project.resolve(value)
            if not p.exists():
                return (
                    f"{self.key}: {value} not found (looked in {p.parent}); give a path relative to the project "
                    "folder or absolute"
                )
        if self.check is not None:
            msg = self.check(value, project)
            if msg:
                return f"{self.key}: {msg}"
        return None

    def get_list_len(self, project: Project) -> int:
        parts, _ = self._split()
        obj: Any = project
        for p in parts:
            obj = getattr(obj, p)
        return len(obj)

    def text_error(self, text: str, project: Project) -> tuple[Any, str | None]:
        """Parse and validate ``text``: (value, message or None)."""
        try:
            value = self.parse(text)
        except Invalid as e:
            return None, f"{self.key}: {e}" + (f" ({self.unit})" if self.unit else "")
        return value, self.validate(value, project)

    def help_line(self, project: Project) -> str:
        d = self.default()
        dtext = ""
        ph = self.placeholder(project) if callable(self.placeholder) else self.placeholder
        if ph:
            dtext = f" Default: {ph}."
        elif d not in (None, "", []):
            dtext = f" Default: {self.format(d)}{' ' + self.unit if self.unit else ''}."
        unit = f" [{self.unit}]" if self.unit else ""
        text = self.help if self.help.endswith((".", ")")) or not dtext else self.help + "."
        return f"{self.key}{unit}: {text}{dtext}"


def field_errors(fields: list[Field], project: Project) -> list[str]:
    """Messages of the visible fields whose current project value does not pass."""
    out = []
    for f in fields:
        if f.visible(project):
            msg = f.validate(f.get(project), project)
            if msg:
                out.append(msg)
    return out
