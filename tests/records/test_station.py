"""`fieldtool station`: a watched folder of clips measured once each with a site's fixed geometry.

Clips are copies of one short synthetic render (0.5 s, the size of tests/records/test_batch.py's); the level is the
render's true level given as a gauge reading. Every wait is bounded."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fieldtool.records import station as st
from fieldtool.records.history import History
from fieldtool.records.sites import create_site, load_site

PY = sys.executable
RUN_S = 240  # the longest any station run here may take


@pytest.fixture(scope="module")
def station_site(rendered, tmp_path_factory):
    """A site made from a short oblique render (test_batch's); its video (a clip) and its true level."""
    from fieldtool.project.model import load_project

    root = tmp_path_factory.mktemp("station")
    truth = rendered("oblique", duration_s=0.5, seed=11)
    p = load_project(truth.project_path)
    p.uncertainty.n_draws = 60  # the interval's draws: fewer, as the test only needs one
    create_site("cam1", p, root / "sites")
    return {"sites": root / "sites", "clip": p.resolve(p.video.path), "level": truth.water_level_m}


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2]) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _args(s, incoming: Path, db: Path, *extra) -> list[str]:
    return [
        PY,
        "-m",
        "fieldtool.cli",
        "station",
        "cam1",
        "--incoming",
        str(incoming),
        "--sites",
        str(s["sites"]),
        "--db",
        str(db),
        "--gauge",
        str(s["level"]),
        "--poll-s",
        "0.2",
        *extra,
    ]


def _journal(db: Path, incoming: Path, state: str | None = None) -> list[st.JournalRow]:
    if not db.exists():
        return []
    with History(db, create=False) as h:
        try:
            return st.journal(h, "cam1", incoming, state)
        except Exception:  # noqa: BLE001 - the schema is being created by the station
            return []


def _wait(cond, timeout: float, what: str, proc: subprocess.Popen | None = None):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = cond()
        if v:
            return v
        if proc is not None and proc.poll() is not None:
            out = proc.stdout.read() if proc.stdout else ""
            raise AssertionError(f"the station ended (rc {proc.returncode}) before {what}: {out}")
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def _stop(proc: subprocess.Popen) -> tuple[int, str]:
    proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=RUN_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return proc.returncode, out


# ---------------------------------------------------------------------------------------------
# pure parts


def test_level_file_interpolates_within_the_gap(tmp_path):
    f = tmp_path / "levels.csv"
    f.write_text("time,level\n2024-05-01T10:00:00Z,10.00\n2024-05-01T11:00:00Z,10.30\n1714435200,9.0\n")
    rows = st.read_level_file(f)
    assert [h for _, h in rows] == [9.0, 10.0, 10.3]  # sorted; Unix 1714435200 is 2024-04-30T00:00Z
    t = rows[1][0] + 1800
    assert st.level_at(rows, t, 3600) == pytest.approx(10.15)
    assert st.level_at(rows, rows[2][0] + 600, 3600) == pytest.approx(10.3)  # nearest, within the gap
    assert st.level_at(rows, rows[2][0] + 7200, 3600) is None
    f.write_text("time,level\nyesterday,10\n")
    with pytest.raises(Exception, match="line 2"):
        st.read_level_file(f)


def test_level_sources_in_the_sites_order(station_site, tmp_path):
    site = load_site("cam1", station_site["sites"])
    cfg = st.station_config(site, gauge_m=10.0)
    assert cfg.level_sources == ("waterline", "file", "gauge")
    ch, why = st.level_choices(site, cfg, Path("a.mp4"), "2024-05-01T10:00:00Z", None)
    assert [c.source for c in ch] == ["gauge"] and any("waterline" in w for w in why) and any("file" in w for w in why)
    rows = [(st._parse_level_time("2024-05-01T10:00:00Z", "t"), 9.5)]
    ch, _ = st.level_choices(site, cfg, Path("a.mp4"), "2024-05-01T10:10:00Z", rows)
    assert [(c.source, c.level_m) for c in ch] == [("file", 9.5), ("gauge", 10.0)]
    # the site's [station] table chooses the order; the command line overrides it
    toml = site.folder / "site.toml"
    toml.write_text(toml.read_text() + '\n[station]\nlevel_sources = ["gauge", "file"]\nstable_s = 2.5\n')
    cfg = st.station_config(site, gauge_m=10.0)
    assert cfg.level_sources == ("gauge", "file") and cfg.stable_s == 2.5
    assert st.station_config(site, level_order="file").level_sources == ("file",)
    with pytest.raises(Exception, match="level sources"):
        st.station_config(site, level_order="radar")
    toml.write_text(toml.read_text().split("\n[station]")[0])


def test_watcher_waits_for_a_stable_clip_or_a_marker(tmp_path):
    now = [0.0]
    w = st.Watcher(stable_s=3.0, clock=lambda: now[0])
    a = tmp_path / "a.mp4"
    a.write_bytes(b"x" * 10)
    assert w.ready([a]) == []
    now[0] = 2.0
    with open(a, "ab") as fh:
        fh.write(b"y")
    assert w.ready([a]) == []  # grew: the clock starts again
    now[0] = 4.5
    assert w.ready([a]) == []
    now[0] = 5.1
    assert [p for p, _, _ in w.ready([a])] == [a]
    b = tmp_path / "b.mp4"
    b.write_bytes(b"z")
    assert w.ready([b]) == []
    (tmp_path / "b.mp4.done").write_text("")
    assert [p for p, _, _ in w.ready([b])] == [b]  # the marker: at once


def test_second_station_refused_and_a_killed_ones_lock_is_free(station_site, tmp_path):
    inc = tmp_path / "in"
    inc.mkdir()
    with st.StationLock(inc):
        r = subprocess.run(
            _args(station_site, inc, tmp_path / "h.sqlite"), capture_output=True, text=True, env=_env(), timeout=60
        )
        assert r.returncode == 2 and "another fieldtool station" in r.stderr and str(os.getpid()) in r.stderr
        assert st.StationLock(inc).held_by_other() == str(os.getpid())
    # a process killed while holding the lock leaves none behind
    holder = subprocess.Popen(
        [
            PY,
            "-c",
            "import sys, time; from fieldtool.records.station import StationLock; "
            f"StationLock(__import__('pathlib').Path({str(inc)!r})).acquire(); print('held', "
            "flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    assert holder.stdout.readline().strip() == "held"
    assert st.StationLock(inc).held_by_other() == str(holder.pid)
    holder.send_signal(signal.SIGKILL)
    holder.wait(10)
    assert st.StationLock(inc).held_by_other() is None
    with st.StationLock(inc):
        pass


# ---------------------------------------------------------------------------------------------
# the station at work


def test_slow_copy_is_measured_once_after_it_is_complete(station_site, tmp_path):
    inc, db = tmp_path / "in", tmp_path / "h.sqlite"
    inc.mkdir()
    proc = subprocess.Popen(
        _args(station_site, inc, db, "--stable-s", "1.5"),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=_env(),
    )
    try:
        blob = station_site["clip"].read_bytes()
        n = 8
        with open(inc / "slow.mp4", "wb") as fh:  # written in chunks over about 3 s
            for k in range(n):
                fh.write(blob[k * len(blob) // n : (k + 1) * len(blob) // n])
                fh.flush()
                time.sleep(0.4)
                assert not _journal(db, inc), "the clip was read while it was still being written"
        done = _wait(lambda: _journal(db, inc, "done"), RUN_S, "the clip measured", proc)
        time.sleep(1.0)  # a second look at the folder must not measure it again
    finally:
        rc, out = _stop(proc)
    assert rc == 0, out
    assert len(done) == 1 and done[0].size == len(blob) and done[0].attempts == 1
    assert len(_journal(db, inc)) == 1
    with History(db, create=False) as h:
        rows = h.query(site="cam1")
    assert len(rows) == 1 and rows[0].id == done[0].measurement_id and rows[0].grade
    assert "SIGTERM received, stopping" in out and "stopped (1 measured, 0 failed)" in out


def test_killed_station_resumes_without_redoing_or_losing_a_clip(station_site, tmp_path):
    inc, db = tmp_path / "in", tmp_path / "h.sqlite"
    inc.mkdir()
    names = [f"c{i}.mp4" for i in range(3)]
    for nm in names:
        shutil.copy(station_site["clip"], inc / nm)
        (inc / (nm + ".done")).write_text("")
    proc = subprocess.Popen(
        _args(station_site, inc, db), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env()
    )
    try:
        _wait(
            lambda: len(_journal(db, inc, "done")) >= 1 and _journal(db, inc, "running"),
            RUN_S,
            "one clip done and the next in flight",
            proc,
        )
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    before = {r.path: r for r in _journal(db, inc, "done")}
    assert 1 <= len(before) < 3
    r = subprocess.run(
        _args(station_site, inc, db, "--exit-when-idle", "1.5"),
        capture_output=True,
        text=True,
        env=_env(),
        timeout=RUN_S,
    )
    assert r.returncode == 0, r.stderr + r.stdout
    assert "left in flight by a stopped station: measured again" in r.stdout
    done = _journal(db, inc, "done")
    assert sorted(Path(j.path).name for j in done) == names and len(_journal(db, inc)) == 3
    for j in done:
        if j.path in before:
            assert j.measurement_id == before[j.path].measurement_id  # not redone
    with History(db, create=False) as h:
        rows = h.query(site="cam1")
    assert sorted(Path(m.video_path).name for m in rows) == names  # one row per clip: none twice, none lost
    s = subprocess.run(
        [
            *_args(station_site, inc, db)[:4],
            "status",
            "cam1",
            "--incoming",
            str(inc),
            "--sites",
            str(station_site["sites"]),
            "--db",
            str(db),
        ],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=60,
    )
    assert s.returncode == 0 and "done     3" in s.stdout and "pending  0" in s.stdout and "failed   0" in s.stdout
    assert "not running" in s.stdout


def _drop(inc: Path, clip: Path, n: int) -> list[str]:
    names = [f"clip{i:02d}.mp4" for i in range(n)]
    for nm in names:
        shutil.copy(clip, inc / nm)
    (inc / "broken.mp4").write_bytes(b"this is no video" * 64)
    return names


def _check_outputs(db: Path, inc: Path, out_root: Path, names: list[str]) -> None:
    """History rows, journal and the time series' points match the clips; the broken one is failed."""
    failed = _journal(db, inc, "failed")
    assert [Path(j.path).name for j in failed] == ["broken.mp4"]
    assert "cannot be read as a video" in failed[0].reason
    done = _journal(db, inc, "done")
    assert sorted(Path(j.path).name for j in done) == names
    with History(db, create=False) as h:
        rows = {m.id: m for m in h.query(site="cam1")}
    assert sorted(Path(m.video_path).name for m in rows.values()) == names
    for j in done:
        m = rows[j.measurement_id]
        assert Path(m.video_path).resolve() == Path(j.path)
        assert (
            m.grade in ("good", "doubtful", "unusable")
            and m.discharge_ci95_lo_m3s < m.discharge_m3s < m.discharge_ci95_hi_m3s
        )
        assert set(m.uncertainty_standard) >= {"iso748", "ive"}
    pts = list(csv.DictReader((out_root / "timeseries.csv").open()))
    assert sorted(int(p["id"]) for p in pts) == sorted(rows)
    for p in pts:
        m = rows[int(p["id"])]
        assert float(p["discharge_m3s"]) == m.discharge_m3s and float(p["water_level_m"]) == m.water_level_m
        assert p["grade"] == m.grade and p["time"] == (m.video_time or m.recorded_at)
    assert (out_root / "timeseries.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_clips_dropped_at_once_in_process_with_a_broken_one(station_site, tmp_path):
    inc, db = tmp_path / "in", tmp_path / "h.sqlite"
    inc.mkdir()
    names = _drop(inc, station_site["clip"], 4)
    site = load_site("cam1", station_site["sites"])
    lines: list[str] = []
    with History(db) as h:
        cfg = st.station_config(site, gauge_m=station_site["level"], stable_s=0.3, poll_s=0.2)
        station = st.Station(
            site, station_site["sites"], inc, h, cfg, rerun=str(tmp_path / "series.rrd"), log=lines.append
        )
        assert station.run(max_idle_s=1.0) == 0
    _check_outputs(db, inc, inc / "fieldtool_station", names)
    assert any(ln.startswith("broken.mp4: failed:") for ln in lines)
    assert (tmp_path / "series.rrd").stat().st_size > 0
    # retried on request, and failed again with its reason; the others are not redone
    with History(db) as h:
        assert st.retry_failed(h, "cam1", inc) == 1
        station = st.Station(site, station_site["sites"], inc, h, cfg, log=lines.append)
        station.run(max_idle_s=1.0)
        assert station.n_done == 0 and station.n_failed == 1
    assert _journal(db, inc, "failed")[0].attempts == 2
    # the station's status in the history: `fieldtool history stations`
    out = subprocess.run(
        [PY, "-m", "fieldtool.cli", "history", "stations", "--db", str(db)],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    row = next(ln for ln in out.stdout.splitlines() if ln.startswith("cam1"))
    assert row.split()[1:4] == [str(len(names)), "0", "1"], out.stdout  # done, pending, failed (the broken one)


@pytest.mark.slow
def test_clips_dropped_at_once_on_a_local_dask_cluster(station_site, tmp_path):
    distributed = pytest.importorskip("distributed")
    inc, db = tmp_path / "in", tmp_path / "h.sqlite"
    inc.mkdir()
    names = _drop(inc, station_site["clip"], 4)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", protocol="tcp", dashboard_address=None
    ) as cluster:
        address = cluster.scheduler_address
        r = subprocess.run(
            _args(station_site, inc, db, "--dask", address, "--stable-s", "0.3", "--exit-when-idle", "1.5"),
            capture_output=True,
            text=True,
            env=_env(),
            timeout=RUN_S,
        )
    assert r.returncode == 0, r.stderr + r.stdout
    assert f"Dask {address}" in r.stdout
    _check_outputs(db, inc, inc / "fieldtool_station", names)


def test_level_file_read_again_when_the_logger_appends(station_site, tmp_path):
    f = tmp_path / "levels.csv"
    f.write_text("2024-05-01T10:00:00Z,10.0\n")
    site = load_site("cam1", station_site["sites"])
    with History(tmp_path / "h.sqlite") as h:
        s = st.Station(
            site, station_site["sites"], tmp_path, h, st.station_config(site, level_file=str(f)), log=lambda _l: None
        )
        assert len(s._levels()) == 1
        with open(f, "a") as fh:
            fh.write("2024-05-01T10:10:00Z,10.1\n")
        assert [lv for _, lv in s._levels()] == [10.0, 10.1]
