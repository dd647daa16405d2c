"""The measurement history: every run in an embedded SQLite database, with reference discharges.

Where: ``--db PATH``, else the ``FIELDTOOL_DB`` environment variable, else
``<user data folder>/history.sqlite`` (see :func:`fieldtool.records.user_data_dir`).

Safety:

- WAL journal, and every write in ``BEGIN IMMEDIATE`` with a busy timeout: one writer at a time,
  readers never block, and two processes recording at once both succeed (they queue).
- The schema is versioned with ``PRAGMA user_version``; a file from a newer fieldtool is refused.
- A file that is not a SQLite database, or a damaged one, is refused with a message and is never
  written to: it is checked read-only (header, then ``PRAGMA quick_check``) before it is opened for
  writing.

Times are stored as ISO 8601 UTC text (``2024-05-01T10:22:33Z``) so that they sort and compare
as text. Discharges in m³/s, levels in metres, velocities in m/s.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import re
import sqlite3
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, fields
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing.paths import is_pattern, literal_glob
from fieldtool.project.model import project_to_dict
from fieldtool.records import user_data_dir

SCHEMA_VERSION = 3
BUSY_TIMEOUT_S = 60.0
REFERENCE_METHODS = ("current_meter", "adcp", "gauge", "other")
_SQLITE_MAGIC = b"SQLite format 3\x00"

_SCHEMA_V1 = """
CREATE TABLE measurements (
    id                  INTEGER PRIMARY KEY,
    site                TEXT NOT NULL DEFAULT '',
    video_time          TEXT,              -- ISO 8601 UTC: when the video was taken
    video_time_source   TEXT,              -- 'container' (mp4/mov creation time) or 'file mtime'
    recorded_at         TEXT NOT NULL,     -- ISO 8601 UTC: when this row was written
    project_name        TEXT NOT NULL DEFAULT '',
    video_path          TEXT NOT NULL DEFAULT '',
    water_level_m       REAL,
    water_level_method  TEXT,
    discharge_m3s       REAL,
    discharge_p05_m3s   REAL,              -- 5th percentile of the per-pair discharges
    discharge_p95_m3s   REAL,              -- 95th percentile of the per-pair discharges
    mean_velocity_ms    REAL,
    alpha               REAL,
    wetted_area_m2      REAL,
    wetted_width_m      REAL,
    parameters_json     TEXT NOT NULL,     -- the project dict the run was made with
    tool_version        TEXT NOT NULL DEFAULT '',
    input_hash          TEXT NOT NULL DEFAULT '',
    output_dir          TEXT NOT NULL DEFAULT '',
    warnings_json       TEXT NOT NULL DEFAULT '[]'
);
CREATE INDEX measurements_site_time ON measurements(site, video_time);
CREATE INDEX measurements_hash ON measurements(input_hash);
CREATE TABLE reference_discharges (
    id                  INTEGER PRIMARY KEY,
    measurement_id      INTEGER NOT NULL REFERENCES measurements(id) ON DELETE CASCADE,
    discharge_m3s       REAL NOT NULL,
    method              TEXT NOT NULL,     -- current_meter | adcp | gauge | other
    uncertainty_m3s     REAL,
    note                TEXT NOT NULL DEFAULT '',
    added_at            TEXT NOT NULL
);
CREATE INDEX reference_measurement ON reference_discharges(measurement_id);
"""

# version 2 (issue 27): the quality grade, the Monte Carlo interval and the ISO 748 / IVE block of the run; rows
# written before it keep NULL there (and '{}' for the standard block), so an old history stays readable
_SCHEMA_V2 = """
ALTER TABLE measurements ADD COLUMN discharge_ci95_lo_m3s REAL;
ALTER TABLE measurements ADD COLUMN discharge_ci95_hi_m3s REAL;
ALTER TABLE measurements ADD COLUMN grade TEXT;
ALTER TABLE measurements ADD COLUMN uncertainty_standard_json TEXT NOT NULL DEFAULT '{}';
"""

# version 3 (issue 27): the journal of `fieldtool station`: one row per clip (path, size and mtime) of an incoming
# folder, so that a clip is measured exactly once across restarts (fieldtool/records/station.py)
_SCHEMA_V3 = """
CREATE TABLE station_journal (
    id                  INTEGER PRIMARY KEY,
    site                TEXT NOT NULL,
    incoming            TEXT NOT NULL,     -- the watched folder (resolved)
    path                TEXT NOT NULL,     -- the clip (resolved)
    size                INTEGER NOT NULL,  -- bytes
    mtime_ns            INTEGER NOT NULL,
    state               TEXT NOT NULL,     -- pending | running | done | failed
    reason              TEXT NOT NULL DEFAULT '',
    level_source        TEXT NOT NULL DEFAULT '',
    measurement_id      INTEGER REFERENCES measurements(id) ON DELETE SET NULL,
    out_dir             TEXT NOT NULL DEFAULT '',
    attempts            INTEGER NOT NULL DEFAULT 0,
    updated_at          TEXT NOT NULL,
    UNIQUE (site, path, size, mtime_ns)
);
CREATE INDEX station_journal_folder ON station_journal(site, incoming, state);
"""

# migrations[v] brings a database from version v to v + 1
_MIGRATIONS: dict[int, str] = {0: _SCHEMA_V1, 1: _SCHEMA_V2, 2: _SCHEMA_V3}

# open History objects of this process, per resolved path
_OPEN: dict[str, int] = {}


def default_db_path() -> Path:
    """``FIELDTOOL_DB`` when set, else ``<user data folder>/history.sqlite``."""
    env = os.environ.get("FIELDTOOL_DB", "").strip()
    return Path(env).expanduser() if env else user_data_dir() / "history.sqlite"


def resolve_db_path(arg: str | Path | None) -> Path:
    """The database path from a ``--db`` argument (None = the default)."""
    return Path(arg).expanduser() if arg else default_db_path()


def utc_now() -> str:
    return _iso(datetime.now(UTC))


def _iso(dt: datetime) -> str:
    return dt.astimezone(UTC).replace(microsecond=0).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_time(text: str, what: str = "time") -> str:
    """A user's date or date-time (``2024-05-01``, ``2024-05-01T10:22``, with or without a zone;
    no zone = UTC) as stored ISO 8601 UTC text."""
    try:
        dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ParameterError(f"{what}: {text!r} is not a date; write it as 2024-05-01 or 2024-05-01T10:22") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return _iso(dt)


# ---------------------------------------------------------------------------------------------
# rows


@dataclass
class Measurement:
    """One row of the history (units in the names)."""

    id: int
    site: str
    video_time: str | None
    video_time_source: str | None
    recorded_at: str
    project_name: str
    video_path: str
    water_level_m: float | None
    water_level_method: str | None
    discharge_m3s: float | None
    discharge_p05_m3s: float | None
    discharge_p95_m3s: float | None
    mean_velocity_ms: float | None
    alpha: float | None
    wetted_area_m2: float | None
    wetted_width_m: float | None
    parameters_json: str
    tool_version: str
    input_hash: str
    output_dir: str
    warnings_json: str
    discharge_ci95_lo_m3s: float | None = None  # Monte Carlo 95 % interval (schema 2; NULL in older rows)
    discharge_ci95_hi_m3s: float | None = None
    grade: str | None = None  # good | doubtful | unusable (schema 2)
    uncertainty_standard_json: str = "{}"  # result.json's uncertainty_standard: ISO 748 and IVE (schema 2)

    @property
    def uncertainty_standard(self) -> dict:
        return json.loads(self.uncertainty_standard_json or "{}")

    @property
    def parameters(self) -> dict:
        return json.loads(self.parameters_json)

    @property
    def warnings(self) -> list[str]:
        return json.loads(self.warnings_json)


_M_COLS = [f.name for f in fields(Measurement)]


@dataclass
class Reference:
    """A reference discharge attached to a measurement (m³/s)."""

    id: int
    measurement_id: int
    discharge_m3s: float
    method: str
    uncertainty_m3s: float | None
    note: str
    added_at: str


_R_COLS = [f.name for f in fields(Reference)]


@dataclass
class ErrorStats:
    """LSPIV discharge against references, for one site (and one reference method, or 'all').

    Errors are (Q_lspiv - Q_ref) / Q_ref in percent; ``rmse_m3s`` in m³/s."""

    site: str
    method: str
    n: int
    bias_percent: float
    mean_abs_percent: float
    rmse_percent: float
    max_abs_percent: float
    rmse_m3s: float


# ---------------------------------------------------------------------------------------------
# the database


class History:
    """An open history database. Use as a context manager, or call :meth:`close`.

    Parameters
    ----------
    path : database file.
    create : create the file (and its folder) when missing; when False a missing file raises
        InputFileError.
    """

    def __init__(self, path: Path | str, create: bool = True) -> None:
        self.path = Path(path)
        exists = self.path.exists()
        if not exists and not create:
            raise InputFileError(
                f"{self.path}: no history database yet; it is created by the first recorded run "
                "(or give another one with --db / FIELDTOOL_DB)"
            )
        self._key = str(self.path.resolve())
        #: True when the file (or its folder) cannot be written: reading works, writing raises
        self.readonly = exists and not _writable(self.path)
        if exists and not _OPEN.get(self._key):
            # every check is made on a read-only connection, before anything may write to the file:
            # a foreign, newer or damaged file is refused byte-identical. Checked once per process: a
            # read-only check beside an open read-write connection of the same process can misread
            # a WAL database that another process is writing.
            _check_existing(self.path)
        elif not exists:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                raise InputFileError(
                    f"{self.path.parent}: cannot create the history's folder ({e.strerror}); "
                    "give another path with --db or FIELDTOOL_DB"
                ) from e
        if self.readonly:
            self.conn = _connect_readonly(self.path)
            self.conn.row_factory = sqlite3.Row
            _OPEN[self._key] = _OPEN.get(self._key, 0) + 1
            self._closed = False
            return
        try:
            self.conn = sqlite3.connect(str(self.path), timeout=BUSY_TIMEOUT_S, isolation_level=None)
        except sqlite3.Error as e:
            raise InputFileError(f"{self.path}: cannot open the history database ({e})") from e
        self.conn.row_factory = sqlite3.Row
        try:
            self.conn.execute("PRAGMA foreign_keys = ON")
            self._ensure_wal()
            self._migrate()
        except sqlite3.OperationalError as e:
            self.conn.close()
            if "readonly" in str(e) or "read-only" in str(e):
                raise InputFileError(
                    f"{self.path}: the history database is read-only ({e}); it cannot be "
                    "created here. Give a writable path with --db or FIELDTOOL_DB"
                ) from e
            raise InputFileError(f"{self.path}: cannot open the history database ({e})") from e
        except BaseException:
            self.conn.close()
            raise
        _OPEN[self._key] = _OPEN.get(self._key, 0) + 1
        self._closed = False

    # -- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        if not self._closed:
            self._closed = True
            _OPEN[self._key] -= 1
        self.conn.close()

    def __enter__(self) -> History:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _ensure_wal(self) -> None:
        mode = self.conn.execute("PRAGMA journal_mode").fetchone()[0]
        if str(mode).lower() == "wal":
            return
        for attempt in range(50):  # another process may be switching it at the same moment
            try:
                self.conn.execute("PRAGMA journal_mode = WAL")
                return
            except sqlite3.OperationalError as e:
                if "locked" not in str(e) and "busy" not in str(e):
                    raise InputFileError(f"{self.path}: cannot switch the history to WAL mode ({e})") from e
                time.sleep(0.05 * (attempt + 1))
        raise InputFileError(f"{self.path}: the history database stayed locked by another program")

    @contextmanager
    def write(self) -> Iterator[sqlite3.Connection]:
        """A write transaction: ``BEGIN IMMEDIATE`` (waits up to BUSY_TIMEOUT_S for another
        writer), committed on success and rolled back on any error. A read-only database raises
        InputFileError saying so."""
        if self.readonly:
            raise InputFileError(
                f"{self.path}: the history database is read-only (no write permission on the file "
                "or its folder, or a read-only disk): it can be listed and exported, not changed. "
                "Copy it somewhere writable and give that path with --db or FIELDTOOL_DB"
            )
        try:
            self.conn.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as e:
            raise InputFileError(
                f"{self.path}: the history is locked by another program for more than "
                f"{BUSY_TIMEOUT_S:.0f} s ({e}); try again when it has finished"
            ) from e
        try:
            yield self.conn
        except BaseException:
            self.conn.execute("ROLLBACK")
            raise
        self.conn.execute("COMMIT")

    def _migrate(self) -> None:
        if self.conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION:
            return  # up to date: no write lock needed
        with self.write() as c:  # checked again under the lock: another process may be migrating
            version = c.execute("PRAGMA user_version").fetchone()[0]
            if version > SCHEMA_VERSION:
                raise InputFileError(
                    f"{self.path}: history written by a newer fieldtool (schema {version}, this one "
                    f"knows up to {SCHEMA_VERSION}); update fieldtool or use another --db"
                )
            if version == 0 and c.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]:
                raise InputFileError(
                    f"{self.path}: this SQLite file holds other tables, not a fieldtool history; "
                    "give another path with --db or FIELDTOOL_DB"
                )
            while version < SCHEMA_VERSION:
                for stmt in _split_sql(_MIGRATIONS[version]):
                    c.execute(stmt)
                version += 1
                c.execute(f"PRAGMA user_version = {version}")

    # -- writing --------------------------------------------------------------------------
    def add_measurement(self, **values: Any) -> int:
        """Insert one measurement; keys are column names of :class:`Measurement` (not ``id``).
        Returns the new id."""
        with self.write() as c:
            return insert_measurement(c, values)

    def record_summary(
        self,
        summary: dict,
        *,
        site: str = "",
        output_dir: str | Path = "",
        video_path: str = "",
        video_time: tuple[str | None, str | None] = (None, None),
        input_hash: str = "",
    ) -> int:
        """Record a run from its ``RunResult.summary()`` dict (``result.json``). Returns the id."""
        return self.add_measurement(
            **summary_values(
                summary,
                site=site,
                output_dir=output_dir,
                video_path=video_path,
                video_time=video_time,
                input_hash=input_hash,
            )
        )

    def add_reference(
        self,
        measurement_id: int,
        discharge_m3s: float,
        method: str,
        uncertainty_m3s: float | None = None,
        note: str = "",
    ) -> int:
        """Attach a reference discharge (m³/s) measured by ``method`` to a measurement."""
        if method not in REFERENCE_METHODS:
            raise ParameterError(f"reference method {method!r}: use one of {', '.join(REFERENCE_METHODS)}")
        if not (math.isfinite(discharge_m3s) and discharge_m3s > 0):
            raise ParameterError(f"reference discharge {discharge_m3s!r} m3/s: give a positive number")
        if uncertainty_m3s is not None and not (math.isfinite(uncertainty_m3s) and uncertainty_m3s >= 0):
            raise ParameterError(f"reference uncertainty {uncertainty_m3s!r} m3/s: give zero or a positive number")
        with self.write() as c:
            if c.execute("SELECT 1 FROM measurements WHERE id = ?", (measurement_id,)).fetchone() is None:
                raise ParameterError(
                    f"measurement {measurement_id}: not in the history {self.path}; "
                    "see `fieldtool history list` for the ids"
                )
            cur = c.execute(
                "INSERT INTO reference_discharges (measurement_id, discharge_m3s, method, uncertainty_m3s, "
                "note, added_at) VALUES (?, ?, ?, ?, ?, ?)",
                (measurement_id, float(discharge_m3s), method, uncertainty_m3s, note, utc_now()),
            )
            assert cur.lastrowid is not None  # an INSERT sets it
            return int(cur.lastrowid)

    def delete_measurement(self, measurement_id: int) -> None:
        """Remove a measurement and its references."""
        with self.write() as c:
            cur = c.execute("DELETE FROM measurements WHERE id = ?", (measurement_id,))
            if cur.rowcount == 0:
                raise ParameterError(f"measurement {measurement_id}: not in the history {self.path}")

    # -- reading --------------------------------------------------------------------------
    def get(self, measurement_id: int) -> Measurement:
        row = self.conn.execute(
            f"SELECT {self._m_select()} FROM measurements WHERE id = ?", (measurement_id,)
        ).fetchone()
        if row is None:
            raise ParameterError(
                f"measurement {measurement_id}: not in the history {self.path}; "
                "see `fieldtool history list` for the ids"
            )
        return Measurement(*row)

    def query(
        self,
        site: str | None = None,
        since: str | None = None,
        until: str | None = None,
        input_hash: str | None = None,
        output_dir: str | None = None,
        limit: int | None = None,
        newest_first: bool = False,
    ) -> list[Measurement]:
        """Measurements filtered by site, video time range [since, until] (stored ISO UTC text,
        see :func:`parse_time`), input hash or output folder, in video-time order."""
        where, args = [], []
        for col, val, op in (
            ("site", site, "="),
            ("video_time", since, ">="),
            ("video_time", until, "<="),
            ("input_hash", input_hash, "="),
            ("output_dir", output_dir, "="),
        ):
            if val is not None:
                where.append(f"{col} {op} ?")
                args.append(val)
        sql = f"SELECT {self._m_select()} FROM measurements"
        if where:
            sql += " WHERE " + " AND ".join(where)
        order = "DESC" if newest_first else "ASC"
        sql += f" ORDER BY video_time {order}, id {order}"
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        return [Measurement(*r) for r in self._select(sql, args)]

    def _m_select(self) -> str:
        """The measurement columns to select: a read-only history of an older schema (not migrated, it cannot
        be written) lacks the newer columns, read as NULL (and '{}' for the standard uncertainty)."""
        if getattr(self, "_m_cols", None) is None:
            have = {r[1] for r in self._select("PRAGMA table_info(measurements)")}
            self._m_cols = ", ".join(
                c if c in have else ("'{}'" if c.endswith("_json") else "NULL") + f" AS {c}" for c in _M_COLS
            )
        return self._m_cols

    def _select(self, sql: str, args=()) -> list:
        """The rows of a read. SQLite answers "disk I/O error" now and then to a reader of a WAL database while
        another process opens or closes it (its shared-memory index is being rebuilt); a read is then tried
        again, up to 5 times over about 0.75 s."""
        for attempt in range(5):
            try:
                return self.conn.execute(sql, args).fetchall()
            except sqlite3.OperationalError as e:
                if "disk I/O error" not in str(e) or attempt == 4:
                    raise
                time.sleep(0.05 * (attempt + 1))
        raise AssertionError("unreachable")

    def sites(self) -> list[str]:
        return [r[0] for r in self._select("SELECT DISTINCT site FROM measurements ORDER BY site")]

    def references(self, measurement_id: int | None = None) -> list[Reference]:
        sql = f"SELECT {', '.join(_R_COLS)} FROM reference_discharges"
        args: tuple = ()
        if measurement_id is not None:
            sql += " WHERE measurement_id = ?"
            args = (measurement_id,)
        return [Reference(*r) for r in self._select(sql + " ORDER BY id", args)]

    def reference_pairs(self, site: str | None = None) -> list[tuple[Measurement, Reference]]:
        """(measurement, reference) for every reference, optionally of one site."""
        out = []
        refs: dict[int, list[Reference]] = {}
        for r in self.references():
            refs.setdefault(r.measurement_id, []).append(r)
        for m in self.query(site=site):
            for r in refs.get(m.id, []):
                out.append((m, r))
        return out

    def station_counts(self, site: str | None = None) -> list[tuple[str, str, dict[str, int], str]]:
        """Per fixed-camera station (site, watched folder) of the journal that ``fieldtool station`` keeps:
        the number of clips in each state (pending, running, done, failed) and the last update (UTC)."""
        sql = "SELECT site, incoming, state, COUNT(*), MAX(updated_at) FROM station_journal"
        args: list = []
        if site is not None:
            sql += " WHERE site = ?"
            args.append(site)
        try:
            rows = self._select(sql + " GROUP BY site, incoming, state ORDER BY site, incoming", args)
        except sqlite3.OperationalError:  # an older history without a journal: no station yet
            return []
        out: dict[tuple[str, str], tuple[dict[str, int], str]] = {}
        for st_site, incoming, state, n, last in rows:
            counts, prev = out.get((st_site, incoming), ({}, ""))
            counts[state] = int(n)
            out[(st_site, incoming)] = (counts, max(prev, last or ""))
        return [(k[0], k[1], c, last) for k, (c, last) in out.items()]

    def error_stats(self, site: str | None = None) -> list[ErrorStats]:
        """Per site, LSPIV against references: over all references ('all') and per method."""
        groups: dict[tuple[str, str], list[tuple[float, float]]] = {}
        for m, r in self.reference_pairs(site):
            if m.discharge_m3s is None:
                continue
            for key in ((m.site, "all"), (m.site, r.method)):
                groups.setdefault(key, []).append((m.discharge_m3s, r.discharge_m3s))
        out = []
        for (s, method), pairs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] != "all", kv[0][1])):
            if method != "all" and len({r for (ss, r) in groups if ss == s and r != "all"}) == 1:
                continue  # a single method: its line would repeat 'all'
            q = [p[0] for p in pairs]
            ref = [p[1] for p in pairs]
            err = [100.0 * (a - b) / b for a, b in zip(q, ref, strict=True)]
            n = len(err)
            out.append(
                ErrorStats(
                    site=s,
                    method=method,
                    n=n,
                    bias_percent=sum(err) / n,
                    mean_abs_percent=sum(abs(e) for e in err) / n,
                    rmse_percent=math.sqrt(sum(e * e for e in err) / n),
                    max_abs_percent=max(abs(e) for e in err),
                    rmse_m3s=math.sqrt(sum((a - b) ** 2 for a, b in zip(q, ref, strict=True)) / n),
                )
            )
        return out

    def integrity_ok(self) -> bool:
        return self.conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def summary_values(
    summary: dict,
    *,
    site: str = "",
    output_dir: str | Path = "",
    video_path: str = "",
    video_time: tuple[str | None, str | None] = (None, None),
    input_hash: str = "",
) -> dict:
    """The columns of one measurement row from a run's ``RunResult.summary()`` dict (``result.json``)."""
    inputs = summary.get("inputs") or {}
    return dict(
        site=site,
        video_time=video_time[0],
        video_time_source=video_time[1],
        project_name=str(inputs.get("name", "")),
        video_path=str(video_path),
        water_level_m=_num(summary.get("water_level_m")),
        water_level_method=summary.get("water_level_method"),
        discharge_m3s=_num(summary.get("discharge_m3s")),
        discharge_p05_m3s=_num(summary.get("discharge_p05_m3s")),
        discharge_p95_m3s=_num(summary.get("discharge_p95_m3s")),
        mean_velocity_ms=_num(summary.get("mean_velocity_ms")),
        alpha=_num(summary.get("alpha")),
        wetted_area_m2=_num(summary.get("wetted_area_m2")),
        wetted_width_m=_num(summary.get("wetted_width_m")),
        parameters_json=json.dumps(inputs, sort_keys=True),
        tool_version=str(summary.get("fieldtool_version", "")),
        input_hash=input_hash,
        output_dir=str(output_dir),
        warnings_json=json.dumps(summary.get("warnings", [])),
        **_uncertainty_columns(summary),
    )


def insert_measurement(c: sqlite3.Connection, values: dict) -> int:
    """Insert one measurement inside an open write transaction (:meth:`History.write`); keys are column
    names of :class:`Measurement` (not ``id``). Returns the new id."""
    unknown = set(values) - set(_M_COLS[1:])
    if unknown:
        raise ValueError(f"unknown history columns: {sorted(unknown)}")
    values = {"recorded_at": utc_now(), "parameters_json": "{}", **values}
    cols = ", ".join(values)
    marks = ", ".join("?" for _ in values)
    rowid = c.execute(f"INSERT INTO measurements ({cols}) VALUES ({marks})", list(values.values())).lastrowid
    assert rowid is not None  # always set after an INSERT
    return int(rowid)


def _uncertainty_columns(summary: dict) -> dict:
    """The schema-2 columns of a ``result.json`` summary: the interval, the grade and the standard block."""
    ci = summary.get("discharge_ci95_m3s") or [None, None]
    q = summary.get("quality")
    quality = q if isinstance(q, dict) else {}
    std = summary.get("uncertainty_standard") if isinstance(summary.get("uncertainty_standard"), dict) else {}
    return {
        "discharge_ci95_lo_m3s": _num(ci[0]),
        "discharge_ci95_hi_m3s": _num(ci[1]),
        "grade": quality.get("grade"),
        "uncertainty_standard_json": json.dumps(std, sort_keys=True),
    }


def _split_sql(script: str) -> list[str]:
    lines = [ln.split("--", 1)[0] for ln in script.splitlines()]
    return [s.strip() for s in "\n".join(lines).split(";") if s.strip()]


def _num(v: Any) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _writable(path: Path) -> bool:
    """Whether this process may write the database and create its -wal/-shm beside it (a
    read-only disk answers no even to root)."""
    return os.access(path, os.W_OK) and os.access(path.parent if str(path.parent) else Path("."), os.W_OK)


def _ro_uri(path: Path, immutable: bool = False) -> str:
    return path.resolve().as_uri() + ("?immutable=1" if immutable else "?mode=ro")


def _connect_readonly(path: Path) -> sqlite3.Connection:
    """A read-only connection that never writes the file nor creates files beside it when it
    cannot: a WAL database in a folder this process cannot write (a read-only mount) is opened as
    immutable, since no one can change it there."""
    immutable = not _writable(path)
    try:
        conn = sqlite3.connect(_ro_uri(path, immutable), uri=True, timeout=BUSY_TIMEOUT_S)
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.OperationalError as e:
        if immutable:
            raise InputFileError(f"{path}: cannot read the history database ({e})") from e
        raise


def _check_existing(path: Path) -> None:
    """Refuse a file that is not a healthy fieldtool history of a schema this version knows,
    without writing to it: header bytes, then on a read-only connection ``PRAGMA quick_check``,
    the schema version and the tables. Nothing beside the file is left behind either."""
    if path.is_dir():
        raise InputFileError(f"{path}: is a folder; give the history database file with --db or FIELDTOOL_DB")
    try:
        with path.open("rb") as fh:
            head = fh.read(len(_SQLITE_MAGIC))
    except OSError as e:
        raise InputFileError(f"{path}: cannot read the history database ({e.strerror})") from e
    if not head:
        return  # an empty file is an empty database: nothing to lose
    advice = (
        "it was left untouched. Move it aside (or restore a backup) and fieldtool starts a new history, "
        "or give another path with --db / FIELDTOOL_DB; `sqlite3 FILE .recover` may rescue the rows"
    )
    if head != _SQLITE_MAGIC:
        raise InputFileError(f"{path}: is not a SQLite database (damaged, or another kind of file); {advice}")
    # a read-only look at a WAL database makes SQLite create the -wal/-shm side files: when the file is
    # refused, remove the ones this check created, so that nothing beside it changes either. A file that
    # passes keeps them: another process may have started to use them meanwhile (removing them then loses
    # its writes), and SQLite removes them when the last connection closes
    sides = [path.with_name(path.name + s) for s in ("-wal", "-shm")]
    existed = [p.exists() for p in sides]

    def tidy() -> None:
        if not existed[0] and sides[0].exists() and sides[0].stat().st_size == 0:
            for p, had in zip(sides, existed, strict=True):
                if not had:
                    p.unlink(missing_ok=True)

    try:
        problem = _quick_check(path)
        if problem is not None:
            problem = f"{problem}; {advice}"
        else:
            problem = _schema_problem(path)
    except BaseException:
        tidy()
        raise
    if problem is not None:
        tidy()
        raise InputFileError(f"{path}: {problem}")


def _schema_problem(path: Path) -> str | None:
    """None when the file is a fieldtool history this version can use (or an empty database);
    else why it is refused. Read-only."""
    conn = _connect_readonly(path)
    try:
        version = int(conn.execute("PRAGMA user_version").fetchone()[0])
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    finally:
        conn.close()
    if version > SCHEMA_VERSION:
        return (
            f"history written by a newer fieldtool (schema {version}, this one knows up to {SCHEMA_VERSION}); "
            "it was left untouched: update fieldtool or use another --db"
        )
    if version == 0 and tables:
        return (
            "this SQLite file holds other tables, not a fieldtool history; it was left untouched: give another "
            "path with --db or FIELDTOOL_DB"
        )
    if version >= 1 and not {"measurements", "reference_discharges"} <= tables:
        return (
            "this SQLite file says it is a fieldtool history but lacks its tables; it was left untouched: "
            "give another path with --db or FIELDTOOL_DB"
        )
    return None


# primary SQLite result codes of a file being written by another connection at that moment
_TRANSIENT = {5: "busy", 6: "locked", 10: "I/O error"}
_CODE_RE = re.compile(r"error code=(\d+)")


def _quick_check(path: Path) -> str | None:
    """``PRAGMA quick_check`` on a read-only connection: None when healthy, else what is wrong.

    A read-only reader can meet a short read or a lock while another process writes (WAL); such
    results are retried for a few seconds before the file is called unreadable."""
    uri = _ro_uri(path, immutable=not _writable(path))  # a read-only disk: nothing can change the file
    last = ""
    for attempt in range(8):
        if attempt:
            time.sleep(min(0.05 * 2**attempt, 1.0))
        try:
            conn = sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_S)
            try:
                res = str(conn.execute("PRAGMA quick_check(1)").fetchone()[0])
            finally:
                conn.close()
        except sqlite3.DatabaseError as e:
            code = getattr(e, "sqlite_errorcode", None)
            if code is not None and code & 0xFF in _TRANSIENT:
                last = str(e)
                continue
            return f"the history database is damaged ({e})"
        if res == "ok":
            return None
        m = _CODE_RE.search(res)
        if m and int(m.group(1)) & 0xFF in _TRANSIENT:
            last = " ".join(res.replace("***", "").split())
            continue
        return f"the history database is damaged ({' '.join(res.replace('***', '').split())})"
    return (
        f"the history database cannot be read reliably ({last}); if no other fieldtool is writing it, "
        "it is damaged (truncated?)"
    )


# ---------------------------------------------------------------------------------------------
# CSV export

CSV_COLUMNS = [
    "id",
    "site",
    "video_time",
    "video_time_source",
    "water_level_m",
    "water_level_method",
    "discharge_m3s",
    "discharge_p05_m3s",
    "discharge_p95_m3s",
    "mean_velocity_ms",
    "alpha",
    "wetted_area_m2",
    "wetted_width_m",
    "reference_discharge_m3s",
    "reference_method",
    "tool_version",
    "input_hash",
    "project_name",
    "video_path",
    "output_dir",
    "recorded_at",
    "parameters_json",
    "discharge_ci95_lo_m3s",
    "discharge_ci95_hi_m3s",
    "grade",
    "iso748_u95_rel",
    "ive_u95_rel",
]


def export_csv(hist: History, rows: list[Measurement]) -> str:
    """CSV text of measurements, one line each; the references of a measurement are joined with
    ';' in the reference columns."""
    refs: dict[int, list[Reference]] = {}
    for r in hist.references():
        refs.setdefault(r.measurement_id, []).append(r)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for m in rows:
        rr = refs.get(m.id, [])
        d = {c: getattr(m, c) for c in _M_COLS}
        d["reference_discharge_m3s"] = ";".join(repr(r.discharge_m3s) for r in rr)
        d["reference_method"] = ";".join(r.method for r in rr)
        std = m.uncertainty_standard
        for key in ("iso748", "ive"):
            d[f"{key}_u95_rel"] = (std.get(key) or {}).get("u95_rel")
        w.writerow(["" if d[c] is None else d[c] for c in CSV_COLUMNS])
    return buf.getvalue()


# ---------------------------------------------------------------------------------------------
# what identifies a run: when the video was taken, and a hash of the inputs

_MP4_EPOCH = datetime(1904, 1, 1, tzinfo=UTC)
_CHUNK = 1 << 20


def _mp4_creation_time(path: Path) -> datetime | None:
    """Creation time from the ``moov/mvhd`` box of an MP4/MOV/3GP file; None if absent or zero.

    Cameras store it as UTC by the standard; a few write local time. Only box headers are read."""
    try:
        size_total = path.stat().st_size
        with path.open("rb") as fh:

            def boxes(start: int, end: int):
                pos = start
                while pos + 8 <= end:
                    fh.seek(pos)
                    hdr = fh.read(8)
                    if len(hdr) < 8:
                        return
                    size, kind = struct.unpack(">I4s", hdr)
                    body = pos + 8
                    if size == 1:
                        ext = fh.read(8)
                        if len(ext) < 8:
                            return
                        size = struct.unpack(">Q", ext)[0]
                        body = pos + 16
                    elif size == 0:
                        size = end - pos
                    if size < 8:
                        return
                    yield kind, body, pos + size
                    pos += size

            for kind, body, end in boxes(0, size_total):
                if kind != b"moov":
                    continue
                for k2, b2, _e2 in boxes(body, end):
                    if k2 != b"mvhd":
                        continue
                    fh.seek(b2)
                    version = fh.read(4)[0]
                    raw = fh.read(8 if version == 1 else 4)
                    secs = struct.unpack(">Q" if version == 1 else ">I", raw)[0]
                    if secs == 0:
                        return None
                    dt = _MP4_EPOCH + timedelta(seconds=secs)
                    if dt.year < 1990 or dt > datetime.now(UTC) + timedelta(days=1):
                        return None
                    return dt
                return None
    except (OSError, struct.error, IndexError, OverflowError):
        return None
    return None


def _video_files(video: Path) -> list[Path]:
    """The file(s) of a clip: one video, or the images of a folder / glob, in name order."""
    if video.is_dir():
        return sorted(p for p in video.iterdir() if p.is_file())
    if is_pattern(video):  # * or ? only: brackets are literal
        return sorted(Path(p) for p in literal_glob(video) if Path(p).is_file())
    return [video] if video.is_file() else []


def video_datetime(video: Path | str) -> tuple[str | None, str | None]:
    """When a clip was taken, as (ISO 8601 UTC text, source): the MP4/MOV container's creation time
    when it has one, else the file's modification time (first image of a sequence)."""
    files = _video_files(Path(video))
    if not files:
        return None, None
    dt = _mp4_creation_time(files[0]) if len(files) == 1 else None
    if dt is not None:
        return _iso(dt), "container"
    return _iso(datetime.fromtimestamp(files[0].stat().st_mtime, UTC)), "file mtime"


def hash_file(path: Path, h: hashlib._Hash | None = None) -> str:
    """SHA-256 of a file, read in 1 MiB chunks."""
    h = h or hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


# project keys that name input files: their content (not their path) enters the hash
_FILE_KEYS = (
    ("video", "path"),
    ("cross_section", "path"),
    ("calibration", "path"),
    ("water_level", "dem_path"),
    ("water_level", "image1"),
    ("water_level", "image2"),
)


def input_hash(project_dict: dict, root: Path | str) -> str:
    """SHA-256 of a run's inputs: the project's parameters plus the bytes of every input file
    (video, cross-section, calibration, DEM, level images), independent of where the files lie.

    ``root`` is the folder relative paths in ``project_dict`` are resolved from."""
    root = Path(root)
    d = json.loads(json.dumps(project_dict))
    d.pop("step", None)  # the TUI's last visited step is not an input
    d.pop("name", None)
    d.get("calibration", {}).pop("checkerboard_video", None)  # only its result (calibration.path) counts
    for table, key in _FILE_KEYS:
        rel = d.get(table, {}).get(key)
        if not rel:
            continue
        p = Path(rel).expanduser()
        p = p if p.is_absolute() else root / p
        files = _video_files(p)
        if not files:
            d[table][key] = f"missing:{Path(rel).name}"
            continue
        h = hashlib.sha256()
        for f in files:
            h.update(f.name.encode() if len(files) > 1 else b"")
            hash_file(f, h)
        d[table][key] = "sha256:" + h.hexdigest()
    return hashlib.sha256(json.dumps(d, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def record_run(project, summary: dict, out_dir: Path | str, *, site: str = "", db: str | Path | None = None) -> int:
    """Record a finished run of ``project`` (a :class:`fieldtool.project.model.Project`) whose
    ``summary`` is ``RunResult.summary()`` and whose results are in ``out_dir``: hashes the inputs,
    reads the video's date, and writes one row to the history at ``db`` (None = the default).
    Returns the new measurement id. For `fieldtool run --record`."""
    video = project.resolve(project.video.path) if project.video.path else None
    vt = video_datetime(video) if video is not None else (None, None)
    h = input_hash(project_to_dict(project), project.root)
    with History(resolve_db_path(db)) as hist:
        return hist.record_summary(
            summary,
            site=site,
            output_dir=Path(out_dir).resolve(),
            video_path=str(video or ""),
            video_time=vt,
            input_hash=h,
        )
