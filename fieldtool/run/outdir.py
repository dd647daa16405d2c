"""An output folder replaced as a unit.

A run claims its output folder before any work (:func:`claim`): it takes a lock beside the folder (a
second run into the same folder is refused, exit 2), refuses a folder that would hold or overwrite
an input (the project's own folder, a folder holding the clip, the image sequence, the cross-section
or any other file the project reads), refuses a read-only folder, and removes the temporary folders
that killed runs left beside it. Everything the run writes (the PIV cache included) goes into a
temporary folder ``.<name>.tmp-<pid>-<random>`` beside the output folder; :meth:`Staging.commit`
swaps it in with one atomic ``renameat2(RENAME_EXCHANGE)``, so that at every moment, even under
``kill -9``, the folder holds either the whole previous run or the whole new one.

Files in the old folder that the new run does not write (the PIV cache when it was reused, a rerun
recording, files the user put there) are carried over as hard links (copies where links are not
possible); outputs the previous run listed in its ``result.json`` and this run did not write are
dropped as stale. A symbolic link given as the output folder stays a link: its target's content is
swapped.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import math
import os
import re
import secrets
import shutil
import signal
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from fieldtool.errors import InputFileError
from fieldtool.project.validation import describe

_RENAME_EXCHANGE = 2
_AT_FDCWD = -100
_GLOB_CHARS = "*?"


class OutputFolderError(InputFileError):
    """The output folder cannot be used (read-only, holds an input, in use by another run): exit 2."""


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2); False where not available."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False  # the call or the file system does not swap: the two-rename fallback
    raise OSError(err, os.strerror(err), str(b))


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


def real_out(out: Path | str) -> Path:
    """The folder a run replaces: ``out`` itself, or the target of ``out`` when it is a symbolic link
    (the link is kept; its target's content is swapped)."""
    out = Path(out).absolute()
    if out.is_symlink():
        return out.resolve()
    return Path(os.path.normpath(out))


def _temp_prefixes(real: Path, given: Path) -> tuple[str, ...]:
    names = {real.name, given.name}
    return tuple(f".{n}.{kind}-" for n in sorted(names) for kind in ("tmp", "old"))


def _pid_of(name: str) -> int | None:
    m = re.search(r"\.(?:tmp|old)-(\d+)-", name)
    return int(m.group(1)) if m else None


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (one of another user counts: it is alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale(real: Path, given: Path | None = None) -> list[Path]:
    """Remove the temporary folders that killed runs left beside ``real`` (``.<name>.tmp-*``, ``.<name>.old-*``);
    called with the folder's lock held, so none of them belongs to a live run of this folder. A folder
    whose owner pid is still alive in this process (another thread) is kept. Returns what was removed."""
    given = real if given is None else Path(given).absolute()
    removed: list[Path] = []
    try:
        entries = list(real.parent.iterdir())
    except OSError:
        return removed
    prefixes = _temp_prefixes(real, given)
    for e in entries:
        if not e.name.startswith(prefixes) or e.is_symlink():
            continue
        pid = _pid_of(e.name)
        if pid == os.getpid() and e.name in _Claim.live_names:
            continue  # another thread's run in this process
        if e.is_dir():
            shutil.rmtree(e, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                e.unlink()
        removed.append(e)
    return removed


def _recover(real: Path) -> None:
    """After a kill between the two renames of the fallback swap (no renameat2), the output folder is
    missing and the previous run sits in ``.<name>.old-*``: put it back."""
    if real.exists() or real.is_symlink():
        return
    olds = sorted(real.parent.glob(f".{_glob_escape(real.name)}.old-*"), key=lambda p: p.stat().st_mtime)
    if olds and olds[-1].is_dir():
        os.rename(olds[-1], real)


def _glob_escape(name: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", name)


def _read_only(mode: int) -> bool:
    """No write bit at all: the owner made it read-only (root, who may write anyway, respects that too)."""
    return not mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)


def _literal_part(path: Path) -> Path:
    """The folder part of a glob pattern before its first wildcard (``frames/*.png`` -> ``frames``)."""
    parts = path.parts
    for i, p in enumerate(parts):
        if any(c in p for c in _GLOB_CHARS):
            return Path(*parts[:i]) if i else Path(".")
    return path


def input_paths(project) -> list[tuple[str, Path]]:
    """(key, absolute path) of every file or folder the project reads (the project file's folder included)."""
    out = []
    for k, spec in describe().items():
        if spec is None or spec.path not in ("file", "video"):
            continue
        table, _, name = k.rpartition(".")
        rel = getattr(getattr(project, table) if table else project, name, "")
        if rel and isinstance(rel, str) and "\x00" not in rel:  # a NUL is no path: the key's check names it
            p = project.resolve(rel)
            out.append((k, _literal_part(p) if not p.exists() else p))
    return out


def _inside(p: Path, folder: Path) -> bool:
    try:
        p.relative_to(folder)
        return True
    except ValueError:
        return False


def check_out(out: Path | str, project=None) -> Path:
    """The real folder a run into ``out`` replaces, after the checks that refuse it (exit 2): not a file,
    not read-only, not the project's folder nor one above it, not a folder holding one of its inputs."""
    given = Path(out).absolute()
    real = real_out(given)
    if real.exists() and not real.is_dir():
        raise OutputFolderError(f"--out {given}: is a file, not a folder; give a folder for the results")
    hint = "give another folder, e.g. out/ beside the project file (the default)"
    if project is not None:
        root = Path(project.root).resolve()
        if real == root or _inside(root, real):
            raise OutputFolderError(
                f"--out {given}: is the project's own folder{' (or one above it)' if real != root else ''}"
                f"; the results would overwrite or sit among its inputs; {hint}"
            )
        for key, p in input_paths(project):
            rp = p.resolve()
            if _inside(rp, real):
                raise OutputFolderError(
                    f"--out {given}: holds {key} ({p}); the results would overwrite or be read as an input; {hint}"
                )
    for folder, what in ((real, "--out"), (real.parent, "the folder of --out")):
        try:
            st = folder.stat()
        except FileNotFoundError:
            continue
        if _read_only(st.st_mode):
            raise OutputFolderError(
                f"{what} {folder}: is read-only (mode {stat.S_IMODE(st.st_mode):04o}); the results "
                "are not written there. Make it writable (chmod u+w) or give another --out"
            )
        if folder == real.parent and not os.access(folder, os.W_OK | os.X_OK):
            raise OutputFolderError(f"{what} {folder}: permission denied; make it writable or give another --out")
    return real


class Staging:
    """Where one run writes its files: ``path`` (a temporary folder beside the output folder);
    ``commit()`` swaps them in as a unit, ``abort()`` drops them. ``out`` may be a symbolic link: its
    target is replaced."""

    def __init__(self, out: Path | str):
        self.given = Path(out).absolute()
        self.out = real_out(self.given)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        if self.out.exists() and not self.out.is_dir():
            raise NotADirectoryError(20, "is a file, not a folder", str(self.out))
        self.t0 = time.time()
        self.done = False
        name = f".{self.out.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}"
        self.path = self.out.parent / name
        os.mkdir(self.path, 0o777)  # the umask applies, as for any folder the user makes
        _Claim.live_names.add(name)

    def commit(self) -> None:
        """Swap the staged folder in. SIGINT and SIGTERM wait until the swap is done (the folder is then
        the new run; the interruption is raised after)."""
        if self.done:
            return
        with _signals_held():
            if not self.out.exists():
                os.rename(self.path, self.out)
                self._finish()
                return
            stale = _listed_outputs(self.out)
            produced = {p.name for p in self.path.iterdir()}
            for entry in self.out.iterdir():
                if entry.name in produced:
                    continue
                if entry.name in stale and _mtime(entry) < self.t0:
                    continue  # an output of the previous run that this run did not write
                _carry(entry, self.path / entry.name)
            if _exchange(self.path, self.out):
                self._finish()  # self.path is now the old run
                shutil.rmtree(self.path, ignore_errors=True)
                return
            old = self.out.parent / f".{self.out.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
            os.rename(self.out, old)
            os.rename(self.path, self.out)
            self._finish()
            shutil.rmtree(old, ignore_errors=True)

    def _finish(self) -> None:
        self.done = True
        _Claim.live_names.discard(self.path.name)

    def abort(self) -> None:
        if not self.done:
            self.done = True
            shutil.rmtree(self.path, ignore_errors=True)
            _Claim.live_names.discard(self.path.name)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back (delivered when the block ends) in the main thread."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


class _Claim:
    """The lock of one output folder, held by one run (one thread) at a time."""

    live_names: set[str] = set()  # temporary folders of the runs alive in this process
    _held: dict[tuple[Path, int], _Claim] = {}
    _guard = threading.Lock()

    def __init__(self, real: Path, given: Path):
        self.real, self.given = real, given
        self.lock_path = real.parent / f".{real.name}.lock"
        self.fd: int | None = None
        self.staging: Staging | None = None
        self.depth = 0

    def acquire(self) -> None:
        self.real.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(20):
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                other = _read_pid(fd)
                os.close(fd)
                who = f" (pid {other})" if other else ""
                raise OutputFolderError(
                    f"--out {self.given}: another fieldtool run{who} is writing into this folder; "
                    "wait for it to end, or give another --out"
                ) from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same:  # not a lock file the previous holder unlinked meanwhile
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self.fd = fd
                return
            os.close(fd)
        raise OutputFolderError(f"--out {self.given}: its lock file {self.lock_path} keeps changing; try again")

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.lock_path)  # while still held: the next run makes a new one
        os.close(self.fd)
        self.fd = None


def _read_pid(fd: int) -> int | None:
    try:
        return int(os.pread(fd, 32, 0).split()[0])
    except (OSError, ValueError, IndexError):
        return None


@contextlib.contextmanager
def claim(out: Path | str, project=None) -> Iterator[Staging]:
    """Claim the output folder ``out`` for one run: the checks of :func:`check_out`, the folder's lock
    (a second run into it is refused with OutputFolderError, exit 2), the removal of what killed runs left
    beside it, and a :class:`Staging` the run writes everything into. The staging is dropped unless
    committed when the block ends (an error, Ctrl-C, SIGTERM). Re-entrant in one thread: a nested claim
    of the same folder yields the same staging."""
    given = Path(out).absolute()
    real = check_out(given, project)
    key = (real, threading.get_ident())
    with _Claim._guard:
        c = _Claim._held.get(key)
    if c is not None:
        assert c.staging is not None  # same thread: the outer claim made its staging before yielding
        c.depth += 1
        try:
            yield c.staging
        finally:
            c.depth -= 1
        return
    c = _Claim(real, given)
    c.acquire()
    try:
        with _Claim._guard:
            _Claim._held[key] = c
        _recover(real)
        sweep_stale(real, given)
        c.staging = Staging(given)
        try:
            yield c.staging
        finally:
            c.staging.abort()  # nothing if committed
    finally:
        with _Claim._guard:
            _Claim._held.pop(key, None)
        c.release()


def _mtime(p: Path) -> float:
    try:
        return p.lstat().st_mtime
    except OSError:
        return 0.0


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
