"""History database, video time, input hash and rating-curve fit."""

from __future__ import annotations

import csv
import io
import os
import sqlite3
import struct
import subprocess
import sys
import textwrap
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from fieldtool.cli.main import main
from fieldtool.errors import InputFileError, ParameterError
from fieldtool.records.history import (
    SCHEMA_VERSION,
    History,
    default_db_path,
    export_csv,
    input_hash,
    parse_time,
    video_datetime,
)
from fieldtool.records.rating import fit_rating


def fake_summary(q: float, level: float, name: str = "m", v: float = 1.0) -> dict:
    return {
        "discharge_m3s": q,
        "discharge_p05_m3s": 0.95 * q,
        "discharge_p95_m3s": 1.05 * q,
        "water_level_m": level,
        "water_level_method": "value",
        "mean_velocity_ms": v,
        "alpha": 0.85,
        "wetted_area_m2": q / v,
        "wetted_width_m": 10.0,
        "warnings": ["w1"],
        "fieldtool_version": "9.9.9",
        "inputs": {"name": name, "piv": {"window_px": 32}},
    }


def fill(h: History) -> list[int]:
    """Two sites, five measurements at known times."""
    rows = [
        ("A", "2024-05-01T08:00:00Z", 2.0, 10.2),
        ("A", "2024-05-03T08:00:00Z", 3.0, 10.4),
        ("B", "2024-05-02T08:00:00Z", 5.0, 3.1),
        ("A", "2024-06-01T08:00:00Z", 4.0, 10.6),
        ("B", "2024-07-01T08:00:00Z", 6.0, 3.3),
    ]
    return [
        h.record_summary(
            fake_summary(q, lv, f"{s}{i}"),
            site=s,
            video_time=(t, "container"),
            output_dir=f"/out/{i}",
            input_hash=f"h{i}",
        )
        for i, (s, t, q, lv) in enumerate(rows)
    ]


def test_default_path_env_and_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv("FIELDTOOL_DB", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert default_db_path() == tmp_path / "xdg" / "fieldtool" / "history.sqlite"
    monkeypatch.setenv("FIELDTOOL_DB", str(tmp_path / "x.sqlite"))
    assert default_db_path() == tmp_path / "x.sqlite"


def test_create_schema_wal_and_queries(tmp_path):
    db = tmp_path / "sub" / "h.sqlite"
    with History(db) as h:
        assert h.conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert h.conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        ids = fill(h)
    with History(db, create=False) as h:  # reopen: schema kept, nothing migrated twice
        assert [m.id for m in h.query()] == [ids[0], ids[2], ids[1], ids[3], ids[4]]  # video-time order
        a = h.query(site="A")
        assert [m.discharge_m3s for m in a] == [2.0, 3.0, 4.0]
        assert a[0].parameters == {"name": "A0", "piv": {"window_px": 32}}
        assert a[0].warnings == ["w1"] and a[0].tool_version == "9.9.9"
        assert a[0].discharge_p95_m3s == pytest.approx(2.1)
        may = h.query(since=parse_time("2024-05-01"), until=parse_time("2024-05-31T23:59:59"))
        assert sorted(m.discharge_m3s for m in may) == [2.0, 3.0, 5.0]
        assert [m.discharge_m3s for m in h.query(newest_first=True, limit=2)] == [6.0, 4.0]
        assert h.query(input_hash="h3")[0].discharge_m3s == 4.0
        assert h.sites() == ["A", "B"]
        assert h.get(ids[2]).water_level_m == 3.1
        with pytest.raises(ParameterError, match="not in the history"):
            h.get(999)


def test_parse_time_zones():
    assert parse_time("2024-05-01") == "2024-05-01T00:00:00Z"
    assert parse_time("2024-05-01T12:00+02:00") == "2024-05-01T10:00:00Z"
    with pytest.raises(ParameterError, match="not a date"):
        parse_time("yesterday")


def test_references_stats_export_delete(tmp_path):
    with History(tmp_path / "h.sqlite") as h:
        ids = fill(h)
        h.add_reference(ids[0], 2.2, "adcp", 0.1, "boat")  # A: (2.0 - 2.2)/2.2 = -9.09 %
        h.add_reference(ids[1], 2.5, "current_meter")  # A: (3.0 - 2.5)/2.5 = +20 %
        h.add_reference(ids[2], 5.0, "gauge")  # B: 0 %
        with pytest.raises(ParameterError, match="method"):
            h.add_reference(ids[0], 1.0, "guess")
        with pytest.raises(ParameterError, match="positive"):
            h.add_reference(ids[0], -1.0, "adcp")
        with pytest.raises(ParameterError, match="not in the history"):
            h.add_reference(12345, 1.0, "adcp")
        stats = {(s.site, s.method): s for s in h.error_stats()}
        e = [100 * (2.0 - 2.2) / 2.2, 100 * (3.0 - 2.5) / 2.5]
        a = stats[("A", "all")]
        assert a.n == 2
        assert a.bias_percent == pytest.approx(np.mean(e))
        assert a.mean_abs_percent == pytest.approx(np.mean(np.abs(e)))
        assert a.rmse_percent == pytest.approx(np.sqrt(np.mean(np.square(e))))
        assert a.max_abs_percent == pytest.approx(20.0)
        assert a.rmse_m3s == pytest.approx(np.sqrt((0.2**2 + 0.5**2) / 2))
        assert stats[("A", "adcp")].n == 1 and stats[("A", "current_meter")].bias_percent == pytest.approx(20.0)
        assert stats[("B", "all")].bias_percent == pytest.approx(0.0)
        assert ("B", "gauge") not in stats  # one method only: no repeated line
        assert [s.site for s in h.error_stats("B")] == ["B"]

        text = export_csv(h, h.query(site="A"))
        rows = list(csv.DictReader(io.StringIO(text)))
        assert [float(r["discharge_m3s"]) for r in rows] == [2.0, 3.0, 4.0]
        assert rows[0]["reference_discharge_m3s"] == "2.2" and rows[0]["reference_method"] == "adcp"
        assert rows[2]["reference_discharge_m3s"] == ""
        assert rows[0]["video_time"] == "2024-05-01T08:00:00Z" and rows[0]["site"] == "A"

        h.delete_measurement(ids[0])
        assert len(h.references()) == 2  # its reference went with it
        assert h.integrity_ok()


def test_cli_history_commands(tmp_path, capsys):
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        ids = fill(h)
    assert main(["history", "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 6 and "/out/4" in out
    assert main(["history", "list", "--db", str(db), "--site", "B", "--until", "2024-06-30"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and "5.0000" in lines[1]
    assert main(["history", "--db", str(db), "reference", str(ids[3]), "5.0", "--method", "adcp"]) == 0
    assert "-20.00 %" in capsys.readouterr().out
    assert main(["history", "stats", "--db", str(db)]) == 0
    assert "-20.00" in capsys.readouterr().out
    out_csv = tmp_path / "e.csv"
    assert main(["history", "export", str(out_csv), "--db", str(db), "--since", "2024-06-01"]) == 0
    assert [r["discharge_m3s"] for r in csv.DictReader(out_csv.open())] == ["4.0", "6.0"]
    assert main(["history", "show", str(ids[3]), "--db", str(db)]) == 0
    assert "reference" in capsys.readouterr().out
    # rating of site A: three points, exact power law not required, just a plot and a line
    png = tmp_path / "r.png"
    assert main(["history", "rating", "A", "--db", str(db), "--out", str(png), "--h0", "10.0"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["history", "rating", "nowhere", "--db", str(db)]) == 2
    assert "no measurements" in capsys.readouterr().err


def test_missing_db_is_not_created_by_reads(tmp_path, capsys):
    db = tmp_path / "none.sqlite"
    assert main(["history", "list", "--db", str(db)]) == 0
    assert "no history yet" in capsys.readouterr().err
    assert not db.exists()
    with pytest.raises(InputFileError, match="no history database"):
        History(db, create=False)


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_corrupt_file_refused_and_untouched(tmp_path, capsys):
    bad = tmp_path / "h.sqlite"
    bad.write_bytes(b"this is a spreadsheet, not a database\n" * 100)
    before = _snapshot(tmp_path)
    with pytest.raises(InputFileError, match="not a SQLite database.*left untouched"):
        History(bad)
    assert main(["history", "list", "--db", str(bad)]) == 2
    assert "left untouched" in capsys.readouterr().err
    assert main(["history", "--db", str(bad), "reference", "1", "2.0", "--method", "adcp"]) == 2
    assert _snapshot(tmp_path) == before  # byte-identical, no -wal/-shm beside it


def test_damaged_database_refused_and_untouched(tmp_path):
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        for _ in range(30):
            fill(h)
        h.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    for extra in ("h.sqlite-wal", "h.sqlite-shm"):
        (tmp_path / extra).unlink(missing_ok=True)
    blob = bytearray(db.read_bytes())
    page = struct.unpack(">H", blob[16:18])[0]
    assert len(blob) >= 4 * page
    blob[2 * page : 3 * page] = b"\xa5" * page  # a table page overwritten
    db.write_bytes(bytes(blob))
    before = _snapshot(tmp_path)
    with pytest.raises(InputFileError, match="damaged.*left untouched"):
        History(db)
    assert _snapshot(tmp_path) == before


def test_newer_schema_and_foreign_sqlite_refused(tmp_path):
    db = tmp_path / "new.sqlite"
    with History(db):
        pass
    c = sqlite3.connect(db)
    c.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    c.close()
    with pytest.raises(InputFileError, match="newer fieldtool"):
        History(db)
    other = tmp_path / "other.sqlite"
    c = sqlite3.connect(other)
    c.execute("CREATE TABLE birds (name TEXT)")
    c.commit()
    c.close()
    with pytest.raises(InputFileError, match="other tables"):
        History(other)


WRITER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from fieldtool.records.history import History
    db, tag, n, go, mode = sys.argv[1], sys.argv[2], int(sys.argv[3]), Path(sys.argv[4]), sys.argv[5]

    def write(h, i):
        h.record_summary({"discharge_m3s": float(i), "water_level_m": 1.0, "inputs": {"name": tag}},
                         site=tag, input_hash=f"{tag}-{i}")

    while not go.exists():
        time.sleep(0.005)
    if mode == "keep":  # one connection for all writes, and a second one of the same process reading
        with History(db) as h:
            for i in range(n):
                write(h, i)
                if i % 10 == 0:
                    with History(db) as h2:
                        h2.query(site=tag)
    else:  # a new connection (and its read-only health check) for every write
        for i in range(n):
            with History(db) as h:
                write(h, i)
""")


def test_two_processes_write_at_once(tmp_path):
    db = tmp_path / "h.sqlite"
    go = tmp_path / "go"
    n = 60
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WRITER, str(db), tag, str(n), str(go), mode],
            env=env,
            stderr=subprocess.PIPE,
            text=True,
        )
        for tag, mode in (("p1", "keep"), ("p2", "reopen"))
    ]
    go.touch()
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    with History(db) as h:
        assert h.integrity_ok()
        for tag in ("p1", "p2"):
            rows = h.query(site=tag)
            assert sorted(int(m.input_hash.split("-")[1]) for m in rows) == list(range(n))
        assert len({m.id for m in h.query()}) == 2 * n


# ---------------------------------------------------------------------------------------------
# video time and input hash


def _box(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I4s", 8 + len(body), kind) + body


def _mp4(created: datetime | None, version: int = 0, mdat_first: bool = True) -> bytes:
    secs = 0 if created is None else int((created - datetime(1904, 1, 1, tzinfo=UTC)).total_seconds())
    if version == 0:
        mvhd = bytes([0, 0, 0, 0]) + struct.pack(">III", secs, secs, 1000) + b"\0" * 84
    else:
        mvhd = bytes([1, 0, 0, 0]) + struct.pack(">QQI", secs, secs, 1000) + b"\0" * 88
    moov = _box(b"moov", _box(b"mvhd", mvhd) + _box(b"trak", b"\0" * 16))
    ftyp = _box(b"ftyp", b"isom\0\0\0\0isom")
    mdat = _box(b"mdat", os.urandom(5000))
    return ftyp + (mdat + moov if mdat_first else moov + mdat)


def test_video_time_from_container_or_mtime(tmp_path):
    when = datetime(2023, 6, 1, 12, 30, 5, tzinfo=UTC)
    for version, first in ((0, True), (1, False)):
        p = tmp_path / f"v{version}.mp4"
        p.write_bytes(_mp4(when, version, first))
        assert video_datetime(p) == ("2023-06-01T12:30:05Z", "container")
    p = tmp_path / "zero.mov"
    p.write_bytes(_mp4(None))
    stamp = datetime(2021, 3, 4, 5, 6, 7, tzinfo=UTC).timestamp()
    os.utime(p, (stamp, stamp))
    assert video_datetime(p) == ("2021-03-04T05:06:07Z", "file mtime")
    seq = tmp_path / "frames"
    seq.mkdir()
    for i in (2, 1):
        (seq / f"f{i}.png").write_bytes(b"x")
        os.utime(seq / f"f{i}.png", (stamp + i, stamp + i))
    assert video_datetime(seq) == ("2021-03-04T05:06:08Z", "file mtime")  # first image by name
    assert video_datetime(tmp_path / "missing.mp4") == (None, None)


def test_input_hash_follows_content_not_location(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        d.mkdir()
        (d / "river.mp4").write_bytes(b"\x01" * 3_000_000)  # more than one hashing chunk
        (d / "xs.csv").write_text("0,1\n5,0\n10,1\n")
    proj = {
        "name": "x",
        "step": "piv",
        "video": {"path": "river.mp4"},
        "cross_section": {"path": "xs.csv"},
        "piv": {"window_px": 32},
    }
    h_a = input_hash(proj, a)
    assert h_a == input_hash({**proj, "name": "other name", "step": "roi"}, b)
    moved = {**proj, "video": {"path": str(a / "river.mp4")}, "cross_section": {"path": "b/xs.csv"}}
    assert h_a == input_hash(moved, tmp_path)
    assert h_a != input_hash({**proj, "piv": {"window_px": 64}}, a)
    with (b / "river.mp4").open("r+b") as fh:
        fh.seek(2_500_000)
        fh.write(b"\x02")
    assert h_a != input_hash(proj, b)


# ---------------------------------------------------------------------------------------------
# rating curve


@pytest.mark.parametrize("a,b,h0", [(4.2, 1.65, 10.1), (25.0, 2.3, 98.0), (0.8, 1.2, -0.35)])
def test_rating_fit_recovers_parameters(a, b, h0):
    rng = np.random.default_rng(7)
    h = np.sort(h0 + rng.uniform(0.15, 1.6, 14))
    q = a * (h - h0) ** b
    c = fit_rating(h, q)
    assert c.a == pytest.approx(a, rel=1e-4) and c.b == pytest.approx(b, rel=1e-4)
    assert c.h0 == pytest.approx(h0, abs=1e-4) and not c.h0_fixed
    assert c.rmse_m3s < 1e-6 * q.max()
    # with 1 % noise: close, and the truth inside about three standard errors
    qn = q * (1 + 0.01 * rng.standard_normal(len(q)))
    c = fit_rating(h, qn)
    assert abs(c.b - b) < max(3 * c.b_se, 0.02 * b)
    assert abs(c.h0 - h0) < max(3 * c.h0_se, 0.02)
    assert c.h0 < h.min()
    assert np.allclose(c.level(c(h)), h)


def test_rating_fixed_h0_and_bad_input():
    h = np.array([1.3, 1.5, 1.8, 2.2, 2.9])
    q = 3.0 * (h - 1.0) ** 1.5
    c = fit_rating(h, q, h0=1.0)
    assert c.h0_fixed and c.h0_se is None
    assert (c.a, c.b) == (pytest.approx(3.0, rel=1e-6), pytest.approx(1.5, rel=1e-6))
    with pytest.raises(ParameterError, match="below the lowest level"):
        fit_rating(h, q, h0=1.3)
    with pytest.raises(ParameterError, match="at least 3"):
        fit_rating(h[:2], q[:2])
    with pytest.raises(ParameterError, match="positive"):
        fit_rating(h, -q)


def test_record_run_of_a_project(tmp_path):
    from fieldtool.project.model import project_from_dict
    from fieldtool.records.history import record_run

    (tmp_path / "v.mp4").write_bytes(_mp4(datetime(2022, 1, 2, 3, 4, 5, tzinfo=UTC)))
    proj = project_from_dict({"name": "p", "video": {"path": "v.mp4"}}, tmp_path)
    db = tmp_path / "h.sqlite"
    mid = record_run(proj, fake_summary(1.5, 2.0), tmp_path / "out", site="S", db=db)
    with History(db) as h:
        m = h.get(mid)
    assert (m.site, m.discharge_m3s, m.video_time) == ("S", 1.5, "2022-01-02T03:04:05Z")
    assert m.video_path == str(tmp_path / "v.mp4") and m.output_dir == str((tmp_path / "out").resolve())
    assert len(m.input_hash) == 64


def test_a_read_is_tried_again_after_a_transient_disk_io_error(tmp_path, monkeypatch):
    """SQLite's "disk I/O error" to a WAL reader while another process opens or closes the database is
    transient: the read is tried again; any other error is raised at once."""
    import sqlite3

    with History(tmp_path / "h.sqlite") as h:
        h.record_summary(
            {"discharge_m3s": 1.0, "water_level_m": 1.0, "inputs": {"name": "a"}}, site="a", input_hash="a-1"
        )
        real = h.conn
        fails = {"n": 2}

        class Flaky:
            def execute(self, sql, args=()):
                if fails["n"] > 0:
                    fails["n"] -= 1
                    raise sqlite3.OperationalError("disk I/O error")
                return real.execute(sql, args)

            def __getattr__(self, name):
                return getattr(real, name)

        h.conn = Flaky()
        try:
            assert [m.site for m in h.query()] == ["a"] and fails["n"] == 0
            fails["n"] = 5  # more than the retries
            with pytest.raises(sqlite3.OperationalError, match="disk I/O"):
                h.query()
        finally:
            h.conn = real


def test_the_check_leaves_the_side_files_another_process_has_started_to_use(tmp_path, monkeypatch):
    """The check of an existing history opens it read-only, which creates its -wal/-shm side files. If another
    process opens the database meanwhile (its -wal still empty), those files are now that process': removing
    them would send its writes to a deleted file (two writers lost rows this way)."""
    import sqlite3

    import fieldtool.records.history as hist

    db = tmp_path / "h.sqlite"
    with History(db) as h:
        fill(h)
    assert not (tmp_path / "h.sqlite-wal").exists()
    other = {}
    real = hist._schema_problem

    def another_process_opens_meanwhile(path):
        other["conn"] = c = sqlite3.connect(str(path), isolation_level=None)
        c.execute("SELECT count(*) FROM measurements").fetchone()  # opened and reading: its -wal is empty
        return real(path)

    monkeypatch.setattr(hist, "_schema_problem", another_process_opens_meanwhile)
    monkeypatch.setattr(hist, "_OPEN", {})
    with History(db) as h:
        n = len(h.query())
    c = other["conn"]
    c.execute("UPDATE measurements SET site = 'kept' WHERE id = (SELECT max(id) FROM measurements)")
    fresh = sqlite3.connect(str(db))
    assert fresh.execute("SELECT count(*) FROM measurements WHERE site = 'kept'").fetchone()[0] == 1
    assert fresh.execute("SELECT count(*) FROM measurements").fetchone()[0] == n
    fresh.close()
    c.close()
