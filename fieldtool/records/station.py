"""A fixed-camera station: every new clip dropped in a folder is measured with a site's fixed geometry.

``fieldtool station SITE --incoming DIR`` watches ``DIR`` (its top level; video files only) and, for each
clip that is complete, writes a visit of the site (:func:`fieldtool.records.sites.new_measurement`), runs
it, records the result in the history (with its grade, its Monte Carlo interval and the ISO 748 / IVE
block), and refreshes the station's plots in ``--out`` (default ``DIR/fieldtool_station``):
``timeseries.png`` (Q with its interval and the level over time, the grade as colour), ``timeseries.csv``
(the points plotted) and ``rating.png`` (the stage-discharge curve, once three measurements span a range
of levels). With ``--rerun FILE.rrd`` or ``--rerun rerun+http://HOST:PORT/proxy`` the series goes to the
rerun stream as well.

Complete clips. A clip is read once its size and modification time have not changed for ``stable_s``
seconds (default 5), or at once when a marker ``CLIP.done`` (or ``CLIP.EXT.done``) lies beside it.

Exactly once. The history database holds a journal (table ``station_journal``): one row per clip, keyed
by site, path, size and modification time (a clip replaced by another of the same name is a new clip).
A clip's measurement and its journal row's ``done`` are written in one transaction, so a station killed
at any moment (even by SIGKILL) restarted later neither measures a clip twice nor loses one: a row left
``running`` is measured again. A failed clip is kept ``failed`` with its reason and is retried only on
request (``fieldtool station retry SITE --incoming DIR``).

One station per folder. ``DIR/.fieldtool_station.lock`` is held with an exclusive ``flock`` while the
station runs; a second station on the same folder is refused naming the first one's process id. The lock
is the kernel's, so a killed station leaves no stale lock behind.

The water level of each clip comes from the first source that has one, in the site's order
(``[station] level_sources`` in ``site.toml``, default ``waterline, file, gauge``; ``--level-order``
overrides it): ``waterline`` — the automatic water line found in the clip, when the site's project uses
``water_level.method = "waterline"`` (a clip where it is not found falls through to the next source);
``file`` — a CSV of ``time,level`` (``--level-file`` or ``[station] level_file``; ISO 8601 times, UTC
unless they carry an offset, or Unix seconds), interpolated at the clip's time (its container date, else
its file time) between rows at most ``level_max_gap_s`` (default 3600 s) from it; ``gauge`` — a reading
given with ``--gauge LEVEL`` (m, the datum of the site's cross-section).

Clips run in this process, one after the other, or with ``--dask tcp://HOST:PORT`` as tasks on the Dask
cluster ``fieldtool batch --scheduler`` uses (the workers must see the same paths). Only this process writes
the history. SIGTERM and SIGINT stop the station after the clip in hand (in-process) or at once (Dask: the
clips in flight are measured again at the next start).
"""

from __future__ import annotations

import csv
import errno
import importlib
import math
import os
import signal
import sqlite3
import threading
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from fieldtool.errors import FieldToolError, InputFileError, ParameterError
from fieldtool.records.batch import VIDEO_EXTS, BatchItem, ItemResult, run_item
from fieldtool.records.history import (
    History,
    insert_measurement,
    parse_time,
    summary_values,
    utc_now,
    video_datetime,
)
from fieldtool.records.sites import SITE_FILE, Site, load_site, new_measurement
from fieldtool.run.outdir import pid_alive

if TYPE_CHECKING:  # rerun is imported only when a stream is asked for
    from fieldtool.viewer.station_log import StationSeries

try:  # the lock; every Unix has it
    fcntl: ModuleType | None = importlib.import_module("fcntl")
except ImportError:  # pragma: no cover - Windows: a process-id file instead
    fcntl = None

LOCK_NAME = ".fieldtool_station.lock"
LEVEL_SOURCES = ("waterline", "file", "gauge")
MARKER = ".done"


# ---------------------------------------------------------------------------------------------
# configuration


@dataclass
class StationConfig:
    """How the station measures. Times in seconds, levels in metres."""

    level_sources: tuple[str, ...] = LEVEL_SOURCES
    level_file: Path | None = None
    level_max_gap_s: float = 3600.0
    level_uncertainty_m: float | None = None
    gauge_m: float | None = None
    stable_s: float = 5.0
    poll_s: float = 1.0


def station_config(
    site: Site,
    *,
    level_order: str | None = None,
    level_file: str | None = None,
    gauge_m: float | None = None,
    level_uncertainty_m: float | None = None,
    stable_s: float | None = None,
    poll_s: float | None = None,
) -> StationConfig:
    """The site's ``[station]`` table of ``site.toml`` (optional), overridden by the arguments given."""
    try:
        table = tomllib.loads((site.folder / SITE_FILE).read_text(encoding="utf-8")).get("station", {})
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputFileError(f"{site.folder / SITE_FILE}: cannot be read ({e})") from e
    if not isinstance(table, dict):
        raise InputFileError(f"{site.folder / SITE_FILE}: [station] must be a table")
    cfg = StationConfig()
    order = level_order if level_order is not None else table.get("level_sources")
    if order is not None:
        names = [s.strip() for s in (order.split(",") if isinstance(order, str) else order) if str(s).strip()]
        bad = [s for s in names if s not in LEVEL_SOURCES]
        if bad or not names:
            raise ParameterError(
                f"level sources {order!r}: use some of {', '.join(LEVEL_SOURCES)}, in the order to "
                "try them (e.g. waterline,file,gauge)"
            )
        cfg.level_sources = tuple(names)
    lf = level_file if level_file is not None else table.get("level_file")
    if lf:
        p = Path(str(lf)).expanduser()
        cfg.level_file = p if p.is_absolute() or level_file is not None else site.folder / p
    for name, given in (
        ("level_max_gap_s", None),
        ("level_uncertainty_m", level_uncertainty_m),
        ("gauge_m", gauge_m),
        ("stable_s", stable_s),
        ("poll_s", poll_s),
    ):
        v = given if given is not None else table.get(name)
        if v is None:
            continue
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise ParameterError(f"[station] {name} = {v!r}: not a number") from None
        if not math.isfinite(v) or (name != "gauge_m" and v < 0):
            raise ParameterError(
                f"[station] {name} = {v!r}: give a finite{' non-negative' if name != 'gauge_m' else ''} number"
            )
        setattr(cfg, name, v)
    return cfg


# ---------------------------------------------------------------------------------------------
# the water level of a clip


def _parse_level_time(text: str, where: str) -> float:
    """Unix seconds (UTC) of a level file's time cell: ISO 8601 (UTC unless an offset is given) or seconds."""
    t = text.strip()
    try:
        return float(t)
    except ValueError:
        pass
    iso = parse_time(t, where)
    return datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()


def read_level_file(path: Path | str) -> list[tuple[float, float]]:
    """(Unix seconds, level m) rows of a ``time,level`` CSV (a header line is optional), sorted by time."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise InputFileError(f"{path}: level file cannot be read ({e.strerror}); give it with --level-file") from e
    rows = []
    delim = ";" if text.count(";") > text.count(",") else ","
    for i, r in enumerate(csv.reader(text.splitlines(), delimiter=delim), 1):
        if not r or not "".join(r).strip() or r[0].lstrip().startswith("#"):
            continue
        if len(r) < 2:
            raise InputFileError(f"{path}, line {i}: write 'time,level' (ISO 8601 UTC time, level in m)")
        try:
            t = _parse_level_time(r[0], f"{path}, line {i}")
            h = float(r[1].strip())
        except (ValueError, FieldToolError):
            if i == 1:
                continue  # the header
            raise InputFileError(
                f"{path}, line {i}: {','.join(r)[:60]!r} is not 'time,level' (ISO 8601 time, level in m)"
            ) from None
        if not math.isfinite(h):
            raise InputFileError(f"{path}, line {i}: the level {r[1]!r} is not a number (m)")
        rows.append((t, h))
    if not rows:
        raise InputFileError(f"{path}: no 'time,level' rows")
    return sorted(rows)


def level_at(rows: list[tuple[float, float]], t: float, max_gap_s: float) -> float | None:
    """The level at Unix time ``t``: linear between the rows around it when both lie within ``max_gap_s``
    of it, else the nearest row within ``max_gap_s``; None when no row is that close."""
    if not rows:
        return None
    before = [r for r in rows if r[0] <= t]
    after = [r for r in rows if r[0] >= t]
    a = before[-1] if before else None
    b = after[0] if after else None
    if a and b and t - a[0] <= max_gap_s and b[0] - t <= max_gap_s:
        return a[1] if b[0] == a[0] else a[1] + (b[1] - a[1]) * (t - a[0]) / (b[0] - a[0])
    near = min((r for r in (a, b) if r), key=lambda r: abs(r[0] - t))
    return near[1] if abs(near[0] - t) <= max_gap_s else None


@dataclass
class LevelChoice:
    """One way to get a clip's level: ``source`` and the level (m; None = found in the clip)."""

    source: str
    level_m: float | None
    uncertainty_m: float | None = None


def level_choices(
    site: Site, cfg: StationConfig, clip: Path, clip_time: str | None, level_rows: list[tuple[float, float]] | None
) -> tuple[list[LevelChoice], list[str]]:
    """The level sources that have a level for ``clip``, in the configured order, and why the others do not."""
    out, why = [], []
    for s in cfg.level_sources:
        if s == "waterline":
            if (site.project.get("water_level") or {}).get("method") == "waterline":
                out.append(LevelChoice("waterline", None))
            else:
                why.append('waterline: the site\'s project does not use water_level.method = "waterline"')
        elif s == "file":
            if level_rows is None:
                why.append("file: no level file (--level-file or [station] level_file)")
                continue
            if clip_time is None:
                why.append(f"file: {clip.name} has no date")
                continue
            t = datetime.fromisoformat(clip_time.replace("Z", "+00:00")).timestamp()
            h = level_at(level_rows, t, cfg.level_max_gap_s)
            if h is None:
                why.append(f"file: no level within {cfg.level_max_gap_s:g} s of {clip_time}")
            else:
                out.append(LevelChoice("file", h, cfg.level_uncertainty_m))
        elif s == "gauge":
            if cfg.gauge_m is None:
                why.append("gauge: no reading (--gauge LEVEL)")
            else:
                out.append(LevelChoice("gauge", cfg.gauge_m, cfg.level_uncertainty_m))
    return out, why


# ---------------------------------------------------------------------------------------------
# the task (runs here or on a Dask worker)


@dataclass
class ClipTask:
    """One clip to measure: the site (by folder), the clip, its folder of results and its level choices."""

    site_name: str
    sites_root: str
    clip: str
    out_dir: str
    choices: list[LevelChoice]
    single_thread: bool = False


@dataclass
class ClipOutcome:
    ok: bool
    result: ItemResult | None = None
    source: str = ""
    reason: str = ""
    notes: list[str] = field(default_factory=list)


def measure_clip(task: ClipTask) -> ClipOutcome:
    """Measure one clip with the first level choice that works (a water line that is not found falls
    through to the next choice). Never raises."""
    notes: list[str] = []
    try:
        site = load_site(task.site_name, task.sites_root)
    except FieldToolError as e:
        return ClipOutcome(False, reason=str(e))
    last = ""
    for c in task.choices:
        visit = Path(task.out_dir)
        try:
            proj = new_measurement(site, task.clip, c.level_m, visit, level_uncertainty_m=c.uncertainty_m, force=True)
        except FieldToolError as e:
            return ClipOutcome(False, reason=str(e), notes=notes)
        r = run_item(
            BatchItem(
                label=Path(task.clip).name, project_path=str(proj), out_dir=str(visit / "results"), site=site.name
            ),
            single_thread=task.single_thread,
        )
        if r.ok:
            return ClipOutcome(True, r, c.source, notes=notes)
        last = r.error or "failed"
        if c.source != "waterline":
            break
        notes.append(f"water line not usable ({last}); next level source")
    return ClipOutcome(False, reason=last or "no level source has a level for this clip", notes=notes)


# ---------------------------------------------------------------------------------------------
# the journal


@dataclass
class JournalRow:
    id: int
    path: str
    size: int
    mtime_ns: int
    state: str
    reason: str
    level_source: str
    measurement_id: int | None
    out_dir: str
    attempts: int
    updated_at: str


_J_COLS = "id, path, size, mtime_ns, state, reason, level_source, measurement_id, out_dir, attempts, updated_at"


def journal(hist: History, site: str, incoming: Path | str, state: str | None = None) -> list[JournalRow]:
    """The journal rows of a site's incoming folder (all, or those in ``state``), oldest first."""
    sql = f"SELECT {_J_COLS} FROM station_journal WHERE site = ? AND incoming = ?"
    args: list = [site, str(Path(incoming).resolve())]
    if state is not None:
        sql += " AND state = ?"
        args.append(state)
    try:
        return [JournalRow(*r) for r in hist._select(sql + " ORDER BY id", args)]
    except sqlite3.OperationalError:  # a read-only history of an older schema: no journal yet
        return []


def retry_failed(hist: History, site: str, incoming: Path | str, clip: str | None = None) -> int:
    """Put failed clips (all, or the one named ``clip``) back to pending; returns how many."""
    sql = (
        "UPDATE station_journal SET state = 'pending', updated_at = ? "
        "WHERE site = ? AND incoming = ? AND state = 'failed'"
    )
    args: list = [utc_now(), site, str(Path(incoming).resolve())]
    if clip:
        sql += " AND (path = ? OR path LIKE ?)"
        args += [str(Path(clip).resolve()), f"%{os.sep}{Path(clip).name}"]
    with hist.write() as c:
        return int(c.execute(sql, args).rowcount)


def _claim(hist: History, site: str, incoming: str, path: str, size: int, mtime_ns: int, out_dir: str) -> int | None:
    """Mark a clip running; None when the journal has it done, failed or running already."""
    with hist.write() as c:
        row = c.execute(
            "SELECT id, state FROM station_journal WHERE site = ? AND path = ? AND size = ? AND mtime_ns = ?",
            (site, path, size, mtime_ns),
        ).fetchone()
        if row is None:
            cur = c.execute(
                "INSERT INTO station_journal (site, incoming, path, size, mtime_ns, state, out_dir, attempts, "
                "updated_at) VALUES (?, ?, ?, ?, ?, 'running', ?, 1, ?)",
                (site, incoming, path, size, mtime_ns, out_dir, utc_now()),
            )
            assert cur.lastrowid is not None  # always set after an INSERT
            return int(cur.lastrowid)
        if row[1] != "pending":
            return None
        c.execute(
            "UPDATE station_journal SET state = 'running', attempts = attempts + 1, out_dir = ?, updated_at = ? "
            "WHERE id = ?",
            (out_dir, utc_now(), row[0]),
        )
        return int(row[0])


def _finish(hist: History, jid: int, outcome: ClipOutcome, site: str) -> int | None:
    """Record the outcome: the measurement and the journal's ``done`` in one transaction; or ``failed``."""
    with hist.write() as c:
        if not outcome.ok:
            c.execute(
                "UPDATE station_journal SET state = 'failed', reason = ?, updated_at = ? WHERE id = ?",
                (outcome.reason, utc_now(), jid),
            )
            return None
        r = outcome.result
        assert r is not None and r.summary is not None  # an ok outcome carries its run's summary
        summary = dict(r.summary)
        if outcome.notes:
            summary["warnings"] = list(summary.get("warnings") or []) + outcome.notes
        mid = insert_measurement(
            c,
            summary_values(
                summary,
                site=site,
                output_dir=Path(r.item.out_dir).resolve(),
                video_path=r.video_path,
                video_time=r.video_time,
                input_hash=r.input_hash,
            ),
        )
        c.execute(
            "UPDATE station_journal SET state = 'done', reason = '', level_source = ?, measurement_id = ?, "
            "updated_at = ? WHERE id = ?",
            (outcome.source, mid, utc_now(), jid),
        )
        return mid


# ---------------------------------------------------------------------------------------------
# the lock


class StationLock:
    """An exclusive lock on ``incoming/.fieldtool_station.lock`` (``flock``: released by the kernel when the
    process ends, however it ends). Raises ParameterError when another station holds it."""

    def __init__(self, incoming: Path):
        self.path = Path(incoming) / LOCK_NAME
        self.fd: int | None = None

    def acquire(self) -> StationLock:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            else:  # pragma: no cover - no flock: a process-id file, stale when that process is gone
                other = os.read(fd, 32).decode(errors="replace").strip()
                if other.isdigit() and int(other) != os.getpid() and pid_alive(int(other)):
                    raise BlockingIOError(errno.EAGAIN, "locked")
        except BlockingIOError:
            os.lseek(fd, 0, os.SEEK_SET)
            other = os.read(fd, 32).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise ParameterError(
                f"{self.path.parent}: another fieldtool station (process {other}) is already watching "
                "this folder; stop it first (one station per folder)"
            ) from None
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd = fd
        return self

    def held_by_other(self) -> str | None:
        """The process id of a station holding the lock now, else None (a probe; takes nothing)."""
        if not self.path.exists():
            return None
        try:
            self.acquire()
        except ParameterError:
            return self.path.read_text(errors="replace").strip() or "?"
        self.release()
        return None

    def release(self) -> None:
        if self.fd is not None:
            try:
                os.ftruncate(self.fd, 0)
                if fcntl is not None:
                    fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = None

    def __enter__(self) -> StationLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ---------------------------------------------------------------------------------------------
# watching the folder


def clip_files(incoming: Path) -> list[Path]:
    """The video files at the top of ``incoming``, by name."""
    return sorted(
        p for p in incoming.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_EXTS and not p.name.startswith(".")
    )


def has_marker(clip: Path) -> bool:
    """``CLIP.done`` or ``CLIP.EXT.done`` beside the clip: the writer says it is complete."""
    return clip.with_suffix(MARKER).exists() or clip.with_name(clip.name + MARKER).exists()


class Watcher:
    """Which clips are complete: a marker file, or size and mtime unchanged for ``stable_s`` seconds."""

    def __init__(self, stable_s: float, clock: Callable[[], float] = time.monotonic):
        self.stable_s = stable_s
        self.clock = clock
        self.seen: dict[str, tuple[int, int, float]] = {}  # path -> (size, mtime_ns, since when unchanged)

    def ready(self, clips: list[Path]) -> list[tuple[Path, int, int]]:
        now = self.clock()
        out = []
        present = set()
        for p in clips:
            try:
                st = p.stat()
            except OSError:
                continue
            key = str(p)
            present.add(key)
            size, mt = st.st_size, st.st_mtime_ns
            old = self.seen.get(key)
            if old is None or old[:2] != (size, mt):
                self.seen[key] = (size, mt, now)
                old = self.seen[key]
            if size > 0 and (has_marker(p) or now - old[2] >= self.stable_s):
                out.append((p, size, mt))
        for k in set(self.seen) - present:
            del self.seen[k]
        return out


# ---------------------------------------------------------------------------------------------
# the station


@dataclass
class StationStatus:
    done: list[JournalRow]
    failed: list[JournalRow]
    running: list[JournalRow]  # in flight now, or left by a station that was killed (measured again at its start)
    pending: list[str]  # clips in the folder the journal does not have done or failed (and retries)
    held_by: str | None  # process id of the station watching the folder now


def status(hist: History, site: str, incoming: Path | str) -> StationStatus:
    incoming = Path(incoming)
    rows = journal(hist, site, incoming)
    settled = {(r.path, r.size, r.mtime_ns) for r in rows if r.state in ("done", "failed", "running")}
    pending = [r.path for r in rows if r.state == "pending"]
    if incoming.is_dir():
        for p in clip_files(incoming):
            st = p.stat()
            key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
            if key not in settled and key[0] not in pending:
                pending.append(key[0])
    return StationStatus(
        [r for r in rows if r.state == "done"],
        [r for r in rows if r.state == "failed"],
        [r for r in rows if r.state == "running"],
        pending,
        StationLock(incoming).held_by_other() if incoming.is_dir() else None,
    )


def clip_out_dir(out_root: Path, clip: Path, size: int, mtime_ns: int) -> Path:
    """The clip's own results folder: its stem and a short key of its size and time (a replaced clip of the
    same name gets a new folder)."""
    return out_root / f"{clip.stem}_{(size ^ mtime_ns) & 0xFFFFFFFF:08x}"


class Station:
    """The watching loop. ``log(line)`` receives one line per event (printed by the CLI)."""

    def __init__(
        self,
        site: Site,
        sites_root: Path,
        incoming: Path,
        hist: History,
        cfg: StationConfig,
        *,
        out_root: Path | None = None,
        dask: str | None = None,
        rerun: str | None = None,
        log: Callable[[str], None] = print,
    ):
        self.site, self.sites_root, self.hist, self.cfg = site, Path(sites_root), hist, cfg
        self.incoming = Path(incoming).resolve()
        self.out_root = Path(out_root).resolve() if out_root else self.incoming / "fieldtool_station"
        self.dask, self.rerun_target, self.log = dask, rerun, log
        self.stop = threading.Event()
        self.series: StationSeries | None = None
        self._level_stamp: tuple[int, int] | None = None
        self.level_rows: list[tuple[float, float]] | None = None
        self._levels()
        self.n_done = self.n_failed = 0

    def _levels(self) -> list[tuple[float, float]] | None:
        """The level file's rows, read again whenever the file changed (a logger appends to it)."""
        f = self.cfg.level_file
        if f is None or "file" not in self.cfg.level_sources:
            return None
        try:
            stt = f.stat()
        except OSError as e:
            raise InputFileError(f"{f}: level file not found ({e.strerror}); give it with --level-file") from e
        stamp = (stt.st_size, stt.st_mtime_ns)
        if stamp != self._level_stamp:
            self.level_rows = read_level_file(f)
            self._level_stamp = stamp
        return self.level_rows

    # -- one clip ---------------------------------------------------------------------------
    def _task(self, clip: Path, size: int, mtime_ns: int) -> tuple[ClipTask | None, str]:
        when, _src = video_datetime(clip)
        try:
            rows = self._levels()
        except FieldToolError as e:  # a level file being rewritten: this clip fails with the reason
            rows = None
            self.log(f"level file: {e}")
        choices, why = level_choices(self.site, self.cfg, clip, when, rows)
        out = clip_out_dir(self.out_root, clip, size, mtime_ns)
        task = ClipTask(
            self.site.name, str(self.sites_root), str(clip), str(out), choices, single_thread=self.dask is not None
        )
        return (task if choices else None), ("no water level for this clip: " + "; ".join(why))

    def _record(self, jid: int, clip: Path, outcome: ClipOutcome) -> None:
        mid = _finish(self.hist, jid, outcome, self.site.name)
        if outcome.ok:
            self.n_done += 1
            assert outcome.result is not None and outcome.result.summary is not None  # ok: _finish recorded it
            s = outcome.result.summary
            ci = s.get("discharge_ci95_m3s") or [None, None]
            grade = (s.get("quality") or {}).get("grade")
            iso = ((s.get("uncertainty_standard") or {}).get("iso748") or {}).get("u95_rel")
            ci_txt = f" (95 %: {ci[0]:.3f} - {ci[1]:.3f})" if ci[0] is not None and ci[1] is not None else ""
            iso_txt = f", ISO 748 ±{100 * iso:.1f} %" if iso is not None else ""
            self.log(
                f"{clip.name}: Q = {s['discharge_m3s']:.4f} m3/s{ci_txt}{iso_txt}, level {s['water_level_m']:.3f} m "
                f"({outcome.source}), {grade or 'no grade'}; measurement {mid}"
            )
        else:
            self.n_failed += 1
            self.log(f"{clip.name}: failed: {outcome.reason}")
            if self.series is not None:
                self.series.failure(clip.name, outcome.reason)
        self.refresh(mid)

    # -- plots ------------------------------------------------------------------------------
    def refresh(self, new_id: int | None = None) -> None:
        """Rewrite timeseries.png/.csv and rating.png from the history (every measurement of the site); the
        measurement ``new_id`` goes to the rerun stream."""
        from fieldtool.plots.station import (
            plot_timeseries,  # matplotlib: imported when the first plot is drawn
        )

        rows: list[dict[str, Any]] = []
        for m in self.hist.query(site=self.site.name):
            rows.append(
                {
                    "id": m.id,
                    "time": m.video_time or m.recorded_at,
                    "discharge_m3s": m.discharge_m3s,
                    "ci95_lo_m3s": m.discharge_ci95_lo_m3s,
                    "ci95_hi_m3s": m.discharge_ci95_hi_m3s,
                    "water_level_m": m.water_level_m,
                    "grade": m.grade,
                    "video_path": m.video_path,
                }
            )
        self.out_root.mkdir(parents=True, exist_ok=True)
        try:
            plot_timeseries(self.out_root / "timeseries.png", rows, site=self.site.name)
            _write_csv(self.out_root / "timeseries.csv", rows)
        except (OSError, ValueError) as e:
            self.log(f"time-series plot not written: {e}")
        pts = [
            (r["water_level_m"], r["discharge_m3s"])
            for r in rows
            if r["water_level_m"] is not None and r["discharge_m3s"] is not None and r["discharge_m3s"] > 0
        ]
        if len(pts) >= 3 and max(h for h, _ in pts) - min(h for h, _ in pts) > 1e-3:
            from fieldtool.records.rating import fit_rating, plot_rating

            try:
                curve = fit_rating([h for h, _ in pts], [q for _, q in pts])
                plot_rating(
                    self.out_root / "rating.png", curve, [h for h, _ in pts], [q for _, q in pts], site=self.site.name
                )
            except (FieldToolError, RuntimeError, ValueError) as e:
                self.log(f"rating curve not refreshed: {e}")
        if self.series is not None and new_id is not None:
            r = next((r for r in rows if r["id"] == new_id), None)
            if r is not None:
                self.series.measurement(
                    r["time"],
                    r["discharge_m3s"],
                    r["ci95_lo_m3s"],
                    r["ci95_hi_m3s"],
                    r["water_level_m"],
                    r["grade"],
                    Path(r["video_path"]).name,
                )
            for w in self.series.warnings:
                self.log(w)
            self.series.warnings.clear()

    # -- the loop ---------------------------------------------------------------------------
    def _states(self) -> dict[tuple[str, int, int], str]:
        """(path, size, mtime_ns) -> state of this folder's journal, in one read (a retry asked for by another
        process shows here as pending)."""
        rows = self.hist._select(
            "SELECT path, size, mtime_ns, state FROM station_journal WHERE site = ? AND incoming = ?",
            (self.site.name, str(self.incoming)),
        )
        return {(r[0], r[1], r[2]): r[3] for r in rows}

    def _candidates(self, watcher: Watcher, busy: set[str]) -> list[tuple[Path, int, int]]:
        out = []
        states = self._states()
        for p, size, mt in watcher.ready(clip_files(self.incoming)):
            path = str(p.resolve())
            if path not in busy and states.get((path, size, mt)) in (None, "pending"):
                out.append((p, size, mt))
        return out

    def run(self, *, max_idle_s: float | None = None) -> int:
        """Watch until stopped (or, with ``max_idle_s``, until nothing was pending for that long). Returns 0."""
        with StationLock(self.incoming):
            with self.hist.write() as c:  # rows a killed station left running: measured again
                n = c.execute(
                    "UPDATE station_journal SET state = 'pending', updated_at = ? WHERE site = ? AND "
                    "incoming = ? AND state = 'running'",
                    (utc_now(), self.site.name, str(self.incoming)),
                ).rowcount
            if n:
                self.log(f"{n} clip(s) left in flight by a stopped station: measured again")
            if self.rerun_target:
                from fieldtool.viewer.station_log import (
                    StationSeries,  # rerun: imported only when asked for
                )

                self.series = StationSeries(self.rerun_target, self.site.name)
            self.log(
                f"station {self.site.name}: watching {self.incoming} (results in {self.out_root}; "
                f"{'Dask ' + self.dask if self.dask else 'in this process'}; level from "
                f"{', '.join(self.cfg.level_sources)})"
            )
            try:
                if self.dask:
                    self._loop_dask(max_idle_s)
                else:
                    self._loop_local(max_idle_s)
            finally:
                if self.series is not None:
                    self.series.close()
            self.log(f"station {self.site.name}: stopped ({self.n_done} measured, {self.n_failed} failed)")
        return 0

    def _start(self, p: Path, size: int, mt: int) -> tuple[int, ClipTask] | None:
        """Claim a clip; a clip without a level fails here with the reason."""
        task, why = self._task(p, size, mt)
        jid = _claim(
            self.hist,
            self.site.name,
            str(self.incoming),
            str(p.resolve()),
            size,
            mt,
            str(clip_out_dir(self.out_root, p, size, mt)),
        )
        if jid is None:
            return None
        if task is None:
            self._record(jid, p, ClipOutcome(False, reason=why))
            return None
        return jid, task

    def _loop_local(self, max_idle_s: float | None) -> None:
        watcher = Watcher(self.cfg.stable_s)
        idle_since = time.monotonic()
        while not self.stop.is_set():
            todo = self._candidates(watcher, set())
            for p, size, mt in todo:
                if self.stop.is_set():
                    break
                started = self._start(p, size, mt)
                if started is None:
                    continue
                jid, task = started
                self._record(jid, p, measure_clip(task))
            if todo or any(True for _ in self._unsettled(watcher)):
                idle_since = time.monotonic()
            if max_idle_s is not None and time.monotonic() - idle_since > max_idle_s:
                return
            self.stop.wait(self.cfg.poll_s)

    def _unsettled(self, watcher: Watcher):
        """Clips seen but not yet complete (still being written)."""
        states = self._states()
        for key, (size, mt, _since) in watcher.seen.items():
            if states.get((str(Path(key).resolve()), size, mt)) in (None, "pending"):
                yield key

    def _loop_dask(self, max_idle_s: float | None) -> None:
        try:
            from distributed import (
                Client,  # imported only with --dask, as `batch --scheduler` does
            )
        except ImportError as e:
            raise ParameterError("--dask needs Dask distributed: pip install 'dask[distributed]'") from e
        try:
            client = Client(self.dask, timeout="20s", set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise ParameterError(
                f"--dask {self.dask}: cannot reach the Dask scheduler ({e}); start it with `dask "
                "scheduler` and workers with `dask worker ADDRESS --nthreads 1`"
            ) from e
        watcher = Watcher(self.cfg.stable_s)
        flight: dict = {}  # future -> (journal id, clip path)
        idle_since = time.monotonic()
        try:
            while not self.stop.is_set():
                busy = {str(p.resolve()) for _, p in flight.values()}
                for p, size, mt in self._candidates(watcher, busy):
                    started = self._start(p, size, mt)
                    if started is not None:
                        jid, task = started
                        f = client.submit(
                            measure_clip, task, key=f"fieldtool-station-{jid}-{time.time_ns()}", pure=False
                        )
                        flight[f] = (jid, p)
                if flight:
                    done = [f for f in flight if f.done()]  # polled: wait() would look for a default client
                    if not done:
                        self.stop.wait(min(self.cfg.poll_s, 0.2))
                        continue
                    for f in done:
                        jid, p = flight.pop(f)
                        try:
                            outcome = f.result()
                        except Exception as e:  # noqa: BLE001 - KilledWorker, lost connection ...
                            outcome = ClipOutcome(False, reason=f"the Dask task failed: {type(e).__name__}: {e}")
                        self._record(jid, p, outcome)
                    idle_since = time.monotonic()
                    continue
                if any(True for _ in self._unsettled(watcher)):
                    idle_since = time.monotonic()
                if max_idle_s is not None and time.monotonic() - idle_since > max_idle_s:
                    return
                self.stop.wait(self.cfg.poll_s)
        finally:
            for f in flight:
                f.cancel()
            if flight:  # measured again at the next start
                with self.hist.write() as c:
                    for jid, _p in flight.values():
                        c.execute(
                            "UPDATE station_journal SET state = 'pending', updated_at = ? WHERE id = ?",
                            (utc_now(), jid),
                        )
            client.close()


def _write_csv(path: Path, rows: list[dict]) -> None:
    cols = ["id", "time", "discharge_m3s", "ci95_lo_m3s", "ci95_hi_m3s", "water_level_m", "grade", "video_path"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r[c] for c in cols])
    tmp.replace(path)


def install_signal_handlers(station: Station) -> None:
    """SIGTERM and SIGINT stop the station cleanly (after the clip in hand)."""

    def handler(signum, _frame):
        station.log(f"station {station.site.name}: {signal.Signals(signum).name} received, stopping")
        station.stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
