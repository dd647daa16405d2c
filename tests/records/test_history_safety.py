"""The history database is never changed before it is known to be ours; a read-only one is read."""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from test_history import fill

from fieldtool.errors import InputFileError
from fieldtool.records.history import SCHEMA_VERSION, History

REPO = Path(__file__).resolve().parents[2]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def _sqlite_file(path: Path, *statements: str) -> None:
    """A database in the rollback-journal mode (as other programs make them): a switch to WAL by
    fieldtool would change bytes 18-19 of its header."""
    c = sqlite3.connect(path)
    for st in statements:
        c.execute(st)
    c.commit()
    c.close()
    assert path.read_bytes()[18:20] == b"\x01\x01"


@pytest.mark.parametrize(
    "statements, match",
    [
        (("CREATE TABLE birds (name TEXT)", "INSERT INTO birds VALUES ('wren')"), "other tables"),
        (("CREATE TABLE measurements (id INTEGER)", f"PRAGMA user_version = {SCHEMA_VERSION + 1}"), "newer fieldtool"),
    ],
)
def test_foreign_or_newer_file_is_refused_byte_identical(tmp_path, statements, match):
    from fieldtool.cli.main import main

    db = tmp_path / "h.sqlite"
    _sqlite_file(db, *statements)
    before = _snapshot(tmp_path)
    with pytest.raises(InputFileError, match=match):
        History(db)
    assert _snapshot(tmp_path) == before  # header unchanged (not switched to WAL), no -wal/-shm
    assert main(["history", "list", "--db", str(db)]) == 2
    assert main(["history", "--db", str(db), "reference", "1", "2.0", "--method", "adcp"]) == 2
    assert _snapshot(tmp_path) == before


def _as_reader(cmd: list[str]) -> subprocess.CompletedProcess:
    """Run the CLI as a process that file modes bind: root ignores them, so as root the command
    runs without the capabilities that override them (util-linux setpriv)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    prefix: list[str] = []
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            pytest.skip("running as root without setpriv: file modes cannot be made to bind")
        prefix = [setpriv, "--bounding-set", "-dac_override,-dac_read_search,-fowner", "--"]
    return subprocess.run(
        [*prefix, sys.executable, "-m", "fieldtool.cli.main", *cmd],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )


@pytest.fixture
def readonly_history():
    """A healthy WAL history in a folder nobody may write (a read-only disk, for SQLite)."""
    folder = Path(tempfile.mkdtemp(prefix="ft_ro_"))
    db = folder / "h.sqlite"
    with History(db) as h:
        fill(h)
    assert not (folder / "h.sqlite-wal").exists()
    db.chmod(0o444)
    folder.chmod(0o555)
    yield db
    folder.chmod(0o755)
    db.chmod(0o644)
    for p in folder.iterdir():
        p.unlink()
    folder.rmdir()


def test_readonly_history_is_listed_and_writing_says_read_only(readonly_history, tmp_path):
    db = readonly_history
    before = _snapshot(db.parent)
    out = tmp_path / "export"
    out.mkdir()
    out.chmod(0o777)
    r = _as_reader(["history", "list", "--db", str(db)])
    assert r.returncode == 0, r.stderr
    assert "damaged" not in r.stderr and r.stdout.count("\n") == 6
    r = _as_reader(["history", "export", str(out / "h.csv"), "--db", str(db)])
    assert r.returncode == 0 and "discharge_m3s" in (out / "h.csv").read_text(), r.stderr
    r = _as_reader(["history", "--db", str(db), "reference", "1", "2.0", "--method", "adcp"])
    assert r.returncode == 2 and "read-only" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert _snapshot(db.parent) == before  # no -wal/-shm, nothing changed
