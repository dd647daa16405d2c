"""Declarations of project keys: unit, range, shape and path rules, attached to the Project
dataclass fields as metadata (``key(...)`` is ``dataclasses.field`` plus a ``KeySpec``).

The rules are enforced by ``fieldtool.project.validation``; a field without a declaration is still checked
there from its type annotation (finite, bounded numbers, non-ragged lists, safe text). Anyone adding
a key to ``project.py`` declares it the same way, on the field's own line::

    start_s: float = key(0.0, unit="s", ge=0.0)  # first frame used ...
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

_MISSING: Any = dataclasses.MISSING


@dataclass(frozen=True)
class KeySpec:
    """Rules of one key (all optional).

    unit : unit of the number(s), for messages ("m", "s", "px", "m/s", "deg", "mm").
    ge, gt, le, lt : bounds of the number, or of every number of a list.
    choices : allowed text values.
    path : "file" (an existing regular file), "video" (file, image folder or glob), "out" (a file name
        written by fieldtool; only text rules), or None (not a path).
    dim : length of each item of a point list (2 for [x, y]); a tuple for several allowed lengths.
    counts : allowed list lengths (e.g. (0, 2)); None = any up to ``max_items``.
    max_items : largest list length.
    text : text rules apply ("name" refuses control characters and bounds the length).
    doc : one-line meaning, used when the trailing comment is not enough.
    """

    unit: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[str, ...] | None = None
    path: str | None = None
    dim: int | tuple[int, ...] | None = None
    counts: tuple[int, ...] | None = None
    max_items: int | None = None
    doc: str = ""


def key(default: Any = _MISSING, *, factory: Any = _MISSING, saved: bool = True, **rules: Any) -> Any:
    """A dataclass field carrying a ``KeySpec`` built from ``rules`` (see KeySpec)."""
    meta: dict[str, object] = {"spec": KeySpec(**rules)}
    if not saved:
        meta["saved"] = False
    if factory is not _MISSING:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def spec_of(f: dataclasses.Field) -> KeySpec | None:
    """The KeySpec of a dataclass field, or None when it has no declaration."""
    return f.metadata.get("spec")
