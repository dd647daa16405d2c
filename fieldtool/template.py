"""`fieldtool init`: a commented project template, generated from the Project dataclasses so the
template, the README's key table and the code never disagree."""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
from pathlib import Path

import tomli_w

from . import project as pj
from .errors import InputFileError

_FIELD = re.compile(r"^\s+(\w+):\s*[^=]+?(?:=.*?)?\s+#\s*(.*)$")


def field_comments(cls: type) -> dict[str, str]:
    """Trailing comments of a dataclass' field lines, by field name."""
    out = {}
    for line in inspect.getsource(cls).splitlines():
        m = _FIELD.match(line)
        if m:
            out[m.group(1)] = m.group(2).strip()
    return out


def _value(v) -> str:
    if isinstance(v, list):
        return json.dumps(v)  # inline array; valid TOML for numbers and strings
    return tomli_w.dumps({"k": v}).split("=", 1)[1].strip()


def sections() -> list[tuple[str, type, object]]:
    """(table name, dataclass, default instance) for every table of the project file."""
    proj = pj.Project()
    out = []
    for f in dataclasses.fields(pj.Project):
        val = getattr(proj, f.name)
        if dataclasses.is_dataclass(val):
            out.append((f.name, type(val), val))
    return out


def template_text() -> str:
    """The commented TOML template. Keys whose default is 'not given' are commented out."""
    top = field_comments(pj.Project)
    lines = [
        "# fieldtool project file. Units are in the key names: _m metres, _s seconds, _px pixels,",
        "# _ms m/s. Pixel coordinates: raw video frame, x right, y down, origin at the top-left pixel centre.",
        "# Relative paths are relative to this file. Run it with: fieldtool run project.toml",
        "",
        f'name = "measurement"  # {top.get("name", "")}',
        f'step = "cross_section"  # {top.get("step", "")}',
        f"filters = []  # {top.get('filters', '')}",
        "",
    ]
    for name, cls, inst in sections():
        doc = (inspect.getdoc(cls) or "").splitlines()
        lines.append(f"[{name}]")
        doc[0] = re.sub(r"^\[\w+\]\s*", "", doc[0]) if doc else ""
        lines += [f"# {d}" if d else "#" for d in doc]
        comments = field_comments(cls)
        for f in dataclasses.fields(cls):
            v = getattr(inst, f.name)
            c = comments.get(f.name, "")
            if v is None:
                lines.append(f"# {f.name} =   # {c}")
            else:
                lines.append(f"{f.name} = {_value(v)}  # {c}")
        lines.append("")
    return "\n".join(lines)


def write_template(folder: Path, force: bool = False) -> Path:
    """Write ``folder/project.toml``; refuse to overwrite unless ``force``."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "project.toml"
    if path.exists() and not force:
        raise InputFileError(f"{path}: already exists; use --force to overwrite it, or choose another folder")
    pj.atomic_write_bytes(path, template_text().encode())
    return path


def key_table_markdown() -> str:
    """Markdown table of every key with its default and comment (for the README)."""
    rows = ["| key | default | meaning (unit) |", "|---|---|---|"]
    top = field_comments(pj.Project)
    for k in ("name", "step", "filters"):
        rows.append(f"| `{k}` | `{_value(getattr(pj.Project(), k))}` | {top.get(k, '')} |")
    for name, cls, inst in sections():
        comments = field_comments(cls)
        for f in dataclasses.fields(cls):
            v = getattr(inst, f.name)
            rows.append(f"| `{name}.{f.name}` | {'not set' if v is None else '`' + _value(v) + '`'} | {comments.get(f.name, '')} |")
    return "\n".join(rows)
