"""An output folder replaced as a unit: a run writes into a temporary folder beside the output
folder and swaps it in at the end, so the folder always holds one consistent run, and a run
killed midway leaves the previous one intact.

Files in the old folder that the new run does not write (the PIV cache, a rerun recording, files
the user put there) are carried over as hard links (copies where links are not possible); outputs
the previous run listed in its ``result.json`` and this run did not write are dropped as stale.
Where the output folder holds the project file itself, files are written in place instead
(``result.json`` last), as moving the project's own folder would surprise its editors.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2); False where not available."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    return fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0


def _carry(src: Path, dst: Path) -> None:
    if src.is_dir() and not src.is_symlink():
        shutil.copytree(src, dst, symlinks=True, copy_function=_link_or_copy)
    else:
        _link_or_copy(src, dst)


def _link_or_copy(src, dst) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


def _listed_outputs(out: Path) -> set[str]:
    """Names the previous run in ``out`` listed in its result.json (its own outputs)."""
    try:
        summary = json.loads((out / "result.json").read_text(encoding="utf-8"))
        files = summary.get("files") if isinstance(summary, dict) else None
        names = {str(v).split("/")[0] for v in (files or {}).values() if isinstance(v, str)}
        return names | {"result.json"}
    except (OSError, ValueError):
        return set()


class Staging:
    """Where one run writes its files: ``path``; ``commit()`` swaps them in, ``abort()`` drops them."""

    def __init__(self, out: Path | str, *, in_place: bool = False):
        self.out = Path(out)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        if self.out.exists() and not self.out.is_dir():
            raise NotADirectoryError(20, "is a file, not a folder", str(self.out))
        self.in_place = in_place
        self.t0 = time.time()
        if in_place:
            self.out.mkdir(exist_ok=True)
            self.path = self.out
        else:
            self.path = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.tmp-", dir=self.out.parent))
            os.chmod(self.path, 0o777 & ~_umask())

    def commit(self) -> None:
        if self.in_place:
            return
        if not self.out.exists():
            os.rename(self.path, self.out)
            return
        stale = _listed_outputs(self.out)
        produced = {p.name for p in self.path.iterdir()}
        for entry in self.out.iterdir():
            if entry.name in produced or entry.name.startswith(f".{self.out.name}.tmp-"):
                continue
            if entry.name in stale and _mtime(entry) < self.t0:
                continue  # an output of the previous run that this run did not write
            _carry(entry, self.path / entry.name)
        if _exchange(self.path, self.out):
            shutil.rmtree(self.path, ignore_errors=True)  # now the old run
            return
        old = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.old-", dir=self.out.parent))
        os.rmdir(old)
        os.rename(self.out, old)
        os.rename(self.path, self.out)
        shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        if not self.in_place:
            shutil.rmtree(self.path, ignore_errors=True)


def _mtime(p: Path) -> float:
    try:
        return p.lstat().st_mtime
    except OSError:
        return 0.0


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def strict_json(obj, warnings: list[str] | None = None, where: str = "") -> object:
    """``obj`` with every non-finite float replaced by None (JSON has no NaN/Infinity); each
    replacement is named in ``warnings``."""
    if isinstance(obj, dict):
        return {k: strict_json(v, warnings, f"{where}.{k}" if where else str(k)) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v, warnings, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, np.ndarray):
        return strict_json(obj.tolist(), warnings, where)
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        if warnings is not None:
            warnings.append(f"{where} is {obj} (not a finite number): written as null")
        return None
    return obj
