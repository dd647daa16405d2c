"""One project file, many editors: the three-way merge every writer of ``project.toml`` goes through.

The TUI, the picking viewer, ``fieldtool calibrate --project`` and ``fieldtool site`` may all have the same
project file open. Each keeps a :class:`ProjectSync`: the file's content as it last read (or wrote) it,
the *base*. On save it re-reads the file (*theirs*) under a lock on the folder, merges base / theirs /
*mine* per key, and per point in point lists (``ortho.gcp_px``, ``section.points_px``, masks ...: merged
per index), and writes atomically only when the merge differs from the file. So a writer never puts back
a value it did not change.

Conflict policy (both changed the same key or the same point to different values): **the file's value
is kept** (the other editor saved it first and shows it already), and the conflict is returned (key,
mine, theirs) so the editor shows both and asks the operator; choosing "mine" is one more save of that
value, which then wins because the base has caught up.

A file that no longer parses (TOML syntax error, unknown key, wrong type) is never written over: the save
raises :class:`ProjectRefused` naming the file and the problem, and nothing is written. A read-only
file (no write bit, e.g. mode 0444) is refused too, and its mode is never changed. A file written
over keeps its mode.

:meth:`ProjectSync.poll` tells an editor, cheaply (one ``stat``: mtime, size, inode), that another
process changed the file, and merges that change into its own values.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import re
import stat as statmod
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w
import tomlkit

from fieldtool.errors import FieldToolError, InputFileError, ParameterError
from fieldtool.project.model import (
    Project,
    _DirLock,
    _merge_into,
    _to_dict,
    project_from_dict,
    project_to_dict,
)
from fieldtool.project.textfile import decode_text, read_bytes
from fieldtool.project.validation import value_problems

MISSING: Any = type("Missing", (), {"__repr__": lambda self: "<missing>"})()


class ProjectRefused(ParameterError):
    """The project file cannot be saved as it is on disk (invalid since another program saved it, or
    read-only); nothing was written. Exit code 2, as every bad input."""


@dataclass(frozen=True)
class Conflict:
    """Both this editor and another changed ``key`` (dotted, ``[i]`` for a point) to different values;
    the file's value (``theirs``) was kept."""

    key: str
    mine: Any
    theirs: Any

    def text(self) -> str:
        return f"{self.key}: another program saved {shown(self.theirs)} (kept); yours was {shown(self.mine)}"


def shown(v: Any) -> str:
    """A value of a conflict as an editor shows it: short floats, "(removed)" for a value taken away."""
    return "(removed)" if v is MISSING or v is None else _short(v)


@dataclass
class SaveResult:
    """What a save (or a poll) did: the project as it is in the file now, whether this call wrote it,
    the conflicts (the file's values kept) and the keys another program had changed meanwhile."""

    project: Project
    written: bool = False
    conflicts: list[Conflict] = field(default_factory=list)
    theirs_changed: list[str] = field(default_factory=list)


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.2f}".rstrip("0").rstrip(".") if abs(v) < 1e6 else f"{v:g}"
    if isinstance(v, list):
        return "[" + ", ".join(_short(x) for x in v) + "]"
    return repr(v) if isinstance(v, str) else str(v)


# ---------------------------------------------------------------------------------------------
# the merge


def _is_seq(v: Any) -> bool:
    return isinstance(v, list) and all(isinstance(x, (list, dict)) for x in v)


def merge3(base: Any, theirs: Any, mine: Any, where: str = "") -> tuple[Any, list[Conflict]]:
    """Three-way merge of plain TOML values (dicts, lists, scalars; ``MISSING`` for a key absent).

    Dicts merge per key; lists of points / tables (every item a list or a dict) merge per index; any
    other value is one unit. A side that did not change a unit takes the other side's value; both
    changed it to different values: the file's value (``theirs``) and a Conflict."""
    if mine == base or mine == theirs:
        return theirs, []
    if theirs == base:
        return mine, []
    parts = [v for v in (base, theirs, mine) if v is not MISSING]
    if parts and all(isinstance(v, dict) for v in parts):
        b, t, m = ({} if v is MISSING else v for v in (base, theirs, mine))
        out: dict = {}
        conflicts: list[Conflict] = []
        for k in list(t) + [k for k in m if k not in t] + [k for k in b if k not in t and k not in m]:
            v, c = merge3(b.get(k, MISSING), t.get(k, MISSING), m.get(k, MISSING), f"{where}.{k}" if where else k)
            conflicts += c
            if v is not MISSING:
                out[k] = v
        return out, conflicts
    if parts and all(_is_seq(v) for v in parts):
        b, t, m = ([] if v is MISSING else v for v in (base, theirs, mine))
        n = max(len(b), len(t), len(m))
        items, conflicts = [], []
        for i in range(n):

            def at(lst, i=i):
                return lst[i] if i < len(lst) else MISSING

            v, c = merge3(at(b), at(t), at(m), f"{where}[{i}]")
            conflicts += c
            items.append(v)
        while items and items[-1] is MISSING:
            items.pop()
        if any(v is MISSING for v in items):  # a hole: one side removed a point the other changed
            return theirs, [Conflict(where, mine, theirs)]
        return items, conflicts
    return theirs, [Conflict(where, mine, theirs)]


def changed_keys(old: Any, new: Any, where: str = "") -> list[str]:
    """Dotted keys (``[i]`` per point) whose values differ between two plain values."""
    if old == new:
        return []
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in list(old) + [k for k in new if k not in old]:
            out += changed_keys(old.get(k, MISSING), new.get(k, MISSING), f"{where}.{k}" if where else k)
        return out
    if _is_seq(old) and _is_seq(new):
        out = []
        for i in range(max(len(old), len(new))):
            out += changed_keys(
                old[i] if i < len(old) else MISSING, new[i] if i < len(new) else MISSING, f"{where}[{i}]"
            )
        return out
    return [where]


def set_dotted(data: dict, dotted: str, value: Any) -> dict:
    """A copy of the plain dict ``data`` with the dotted key set (None / MISSING removes it)."""
    out = _deep_copy(data)
    *head, last = dotted.split(".")
    node = out
    for part in head:
        nxt = node.get(part)
        if not isinstance(nxt, dict):
            nxt = node[part] = {}
        node = nxt
    if value is None or value is MISSING:
        node.pop(last, None)
    else:
        node[last] = _to_dict(value)
    return out


_PART = re.compile(r"([^.\[\]]+)((?:\[\d+\])*)")


def put_mine_back(data: dict, conflicts: list[Conflict]) -> dict:
    """A copy of the plain dict ``data`` with this editor's value of each conflict set again (the operator's
    "put mine back", in the TUI and in the viewer)."""
    for c in conflicts:
        data = set_path(data, c.key, c.mine)
    return data


def set_path(data: dict, key: str, value: Any) -> dict:
    """A copy of the plain dict ``data`` with ``key`` set, where ``key`` is a Conflict's key: dotted, with
    ``[i]`` for an item of a list (``"ortho.gcp_px[1]"``). MISSING or None removes it (a removed last point)."""
    out = _deep_copy(data)
    steps: list[Any] = []
    for name, idx in _PART.findall(key):
        steps.append(name)
        steps += [int(i) for i in re.findall(r"\d+", idx)]
    node: Any = out
    for here, nxt in itertools.pairwise(steps):
        if isinstance(here, int):
            node = node[here]
        else:
            if here not in node or not isinstance(node[here], (dict, list)):
                node[here] = [] if isinstance(nxt, int) else {}
            node = node[here]
    last = steps[-1]
    gone = value is None or value is MISSING
    if isinstance(last, int):
        if gone:
            del node[last:]
        elif last < len(node):
            node[last] = _to_dict(value)
        else:
            node.append(_to_dict(value))
    elif gone:
        node.pop(last, None)
    else:
        node[last] = _to_dict(value)
    return out


def _deep_copy(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _deep_copy(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_deep_copy(x) for x in v]
    return v


# ---------------------------------------------------------------------------------------------
# the file


Stamp = tuple[int, int, int]


def file_stamp(path: Path) -> Stamp | None:
    """(mtime_ns, size, inode) of ``path``; None when it does not exist. Any write through a rename
    changes the inode, so two saves within one mtime tick are still told apart."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def check_writable(path: Path) -> None:
    """Refuse (ProjectRefused) a project file without a write bit (mode 0444) or in a folder this
    process cannot write: fieldtool never replaces a file the user made read-only."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    if not st.st_mode & 0o222 or not os.access(path, os.W_OK):
        raise ProjectRefused(
            f"{path}: the project file is read-only (mode {statmod.S_IMODE(st.st_mode):04o}); "
            "nothing was saved. Make it writable (chmod u+w) to save the entries"
        )
    if not os.access(path.parent, os.W_OK):
        raise ProjectRefused(f"{path.parent}: the project's folder is read-only; nothing was saved")


def _read(path: Path) -> tuple[str | None, dict | None, Stamp | None]:
    """(text, parsed dict, stamp) of the file as it is now; (None, None, None) when it does not exist.
    Raises ProjectRefused when it is not a valid project file (syntax or keys)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None, None, None
    except OSError:
        read_bytes(path, "project file")  # raises InputFileError with the reason
        raise
    try:
        st = os.fstat(fd)
        if not statmod.S_ISREG(st.st_mode):
            os.close(fd)
            fd = -1
            read_bytes(path, "project file")  # refuses a folder / a pipe with its message
        chunks = []
        while True:
            b = os.read(fd, 1 << 20)
            if not b:
                break
            chunks.append(b)
    finally:
        if fd >= 0:
            os.close(fd)
    text, _ = decode_text(b"".join(chunks), path, "project file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ProjectRefused(
            f"{path}: not valid TOML now ({e}; saved so by another program or by hand); "
            "nothing was saved here. Fix the line named (your entries are kept in this window)"
        ) from None
    except RecursionError:
        raise ProjectRefused(f"{path}: values nested too deeply; nothing was saved") from None
    try:
        project_from_dict(data, path.parent)
    except ParameterError as e:
        raise ProjectRefused(
            f"{path}: {e} (saved so by another program or by hand); nothing was saved "
            "here. Fix that key (your entries are kept in this window)"
        ) from None
    return text, data, (st.st_mtime_ns, st.st_size, st.st_ino)


_HEADER = re.compile(r"^\s*\[+\s*([A-Za-z0-9_.\-]+)\s*\]+")


def _uncomment(text: str, added: list[tuple[str, str]]) -> str:
    """Put each key added to a table (tomlkit appends it at the end of the table) on the line where the
    template had it commented out (``# value_m =   # comment``), keeping that line's comment."""
    lines = text.split("\n")
    for table, k in added:
        start, end = 0, len(lines)
        if table:
            found = next(
                (i + 1 for i, ln in enumerate(lines) if (m := _HEADER.match(ln)) and m.group(1) == table), None
            )
            if found is None:
                continue
            start = found
        end = next((i for i in range(start, len(lines)) if _HEADER.match(lines[i])), len(lines))
        key_re = re.compile(rf"^{re.escape(k)}\s*=")
        com_re = re.compile(rf"^#\s*{re.escape(k)}\s*=\s*(?:#\s*(.*))?$")
        new_i = next((i for i in range(start, end) if key_re.match(lines[i])), None)
        com_i = next((i for i in range(start, end) if com_re.match(lines[i])), None)
        if new_i is None or com_i is None or new_i < com_i:
            continue
        com_m = com_re.match(lines[com_i])
        assert com_m is not None  # com_i is a line com_re matched
        note = com_m.group(1)
        if "\n" in lines[new_i] or lines[new_i].rstrip().endswith(("[", "{")):
            continue
        new_line = lines[new_i].rstrip()
        if note and "#" not in new_line:
            new_line += f"  # {note.strip()}"
        lines[com_i] = new_line
        del lines[new_i]
    return "\n".join(lines)


def _dump(old_text: str | None, old: dict | None, new: dict) -> bytes:
    """TOML bytes of ``new``, touching only what differs from ``old_text`` (comments and layout kept)."""
    if old_text is None:
        return tomli_w.dumps(new).encode("utf-8")
    try:
        doc = tomlkit.parse(old_text)
    except Exception:  # noqa: BLE001 - parsed by tomllib already; a tomlkit quirk gives a plain file
        return tomli_w.dumps(new).encode("utf-8")
    _merge_into(doc, new)
    text = tomlkit.dumps(doc)
    old = old or {}
    added = [("", k) for k, v in new.items() if k not in old and not isinstance(v, dict)]
    for t, v in new.items():
        if isinstance(v, dict):
            o_t = old.get(t)
            o = o_t if isinstance(o_t, dict) else {}
            added += [(t, k) for k in v if k not in o]
    return _uncomment(text, added).encode("utf-8") if added else text.encode("utf-8")


def _write(path: Path, data: bytes) -> Stamp:
    """Atomic write (temp file + fsync + rename) keeping the old file's mode; the stamp of what was written."""
    if path.is_symlink():
        path = path.resolve()
    try:
        mode = statmod.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
            st = os.fstat(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return (st.st_mtime_ns, st.st_size, st.st_ino)


class ProjectSync:
    """One editor's view of one project file: the base it last read or wrote, and its stamp.

    ``load()`` reads the file; ``save(mine)`` merges and writes (see the module docstring);
    ``poll(mine)`` returns a SaveResult when another program changed the file since (else None)."""

    def __init__(self, path: Path | str):
        self.path = Path(path).absolute()
        self.base: dict | None = None
        self.stamp: Stamp | None = None
        self.error: str | None = None  # why the file on disk was refused at the last poll/save

    def load(self) -> Project:
        _text, data, stamp = _read(self.path)
        if data is None:
            raise InputFileError(f"{self.path}: project file not found. Create one with `fieldtool init DIR`.")
        project = project_from_dict(data, self.path.parent)
        self.base, self.stamp, self.error = project_to_dict(project), stamp, None
        return project

    def changed_on_disk(self) -> bool:
        return file_stamp(self.path) != self.stamp

    def poll(self, mine: Project | dict | None = None) -> SaveResult | None:
        """When the file changed since this editor last read or wrote it: its project merged with
        ``mine`` (this editor's unsaved values; None = none), the keys changed there, the conflicts.
        Nothing is written. A file that is invalid now sets ``self.error`` and returns None."""
        stamp = file_stamp(self.path)
        if stamp == self.stamp or stamp is None:
            return None
        try:
            _text, theirs, stamp = _read(self.path)
        except FieldToolError as e:
            self.stamp, self.error = stamp, str(e)
            return None
        if theirs is None:
            return None
        self.error = None
        theirs = project_to_dict(project_from_dict(theirs, self.path.parent))
        base = self.base if self.base is not None else theirs
        mine_d = base if mine is None else (project_to_dict(mine) if isinstance(mine, Project) else mine)
        merged, conflicts = merge3(base, theirs, mine_d)
        project = project_from_dict(merged, self.path.parent)
        result = SaveResult(project, False, conflicts, changed_keys(base, theirs))
        self.base, self.stamp = theirs, stamp
        return result

    def save(self, mine: Project | dict) -> SaveResult:
        """Merge ``mine`` into the file as it is now and write what changed (ProjectRefused when the
        file is invalid or read-only; ParameterError when ``mine`` does not make a valid project)."""
        mine_d = project_to_dict(mine) if isinstance(mine, Project) else _deep_copy(mine)
        self.path.parent.mkdir(parents=True, exist_ok=True)  # a new project in a new folder
        with _DirLock(self.path):
            return self._save_locked(mine_d)

    def _save_locked(self, mine_d: dict) -> SaveResult:
        try:
            text, theirs, stamp = _read(self.path)
        except ProjectRefused as e:
            self.error = str(e)
            raise
        if theirs is not None:
            check_writable(self.path)
            theirs = project_to_dict(project_from_dict(theirs, self.path.parent))
            base = self.base if self.base is not None else theirs
            merged, conflicts = merge3(base, theirs, mine_d)
            changed = changed_keys(base, theirs)
        else:
            merged, conflicts, changed = mine_d, [], []
        project = project_from_dict(merged, self.path.parent)
        merged = project_to_dict(project)
        _refuse_bad_values(project, changed_keys(theirs or {}, merged))  # the one validation layer
        written = False
        if theirs is None or merged != theirs:
            stamp = _write(self.path, _dump(text, theirs, merged))
            written = True
        self.base, self.stamp, self.error = merged, stamp, None
        return SaveResult(project, written, conflicts, changed)

    def set_keys(self, changes: dict[str, Any]) -> SaveResult:
        """Set dotted keys (``{"calibration.path": "cal.toml"}``; None removes) on top of the file as it
        is now: the one-shot writers' save (``calibrate --project``, ``site``)."""
        with _DirLock(self.path):
            _text, theirs, stamp = _read(self.path)
            if theirs is not None:
                self.base = project_to_dict(project_from_dict(theirs, self.path.parent))
                self.stamp = stamp
            mine = self.base or {}
            for k, v in changes.items():
                mine = set_dotted(mine, k, v)
            return self._save_locked(mine)


def _refuse_bad_values(project: Project, keys: list[str]) -> None:
    """ParameterError (naming the key) for the first error of a value this writer changes, by itself
    (validation.value_problems: type, range, finiteness; a half-picked point list passes)."""
    tops = sorted({re.sub(r"\[\d+\].*$", "", k) for k in keys})  # "ortho.gcp_px[1]" -> "ortho.gcp_px"
    for problem in value_problems(project, tops):
        if problem.severity == "error":
            raise ParameterError(str(problem))


def adopt(project: Project, merged: Project) -> None:
    """Take every saved value of ``merged`` into ``project`` in place (widgets keep their objects)."""
    for f in dataclasses.fields(Project):
        if not f.metadata.get("saved", True):
            continue
        new = getattr(merged, f.name)
        if dataclasses.is_dataclass(new):
            cur = getattr(project, f.name)
            for sf in dataclasses.fields(new):
                setattr(cur, sf.name, getattr(new, sf.name))
        else:
            setattr(project, f.name, new)
