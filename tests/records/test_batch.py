"""Batch runs: a Dask LocalCluster gives the same discharges as separate runs; failing items are
listed with their reason while the others finish and are recorded."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from fieldtool.cli.main import main
from fieldtool.records.batch import BatchItem, plan_projects, read_levels, run_batch, run_item
from fieldtool.records.history import History


def test_run_item_reports_instead_of_raising(tmp_path):
    r = run_item(BatchItem(label="x", project_path=str(tmp_path / "nope.toml"), out_dir=str(tmp_path / "o")))
    assert not r.ok and "nope.toml" in r.error and "not found" in r.error
    bad = tmp_path / "bad.toml"
    bad.write_text("[piv]\nwindow_px = 'large'\n")
    r = run_item(BatchItem(label="bad", project_path=str(bad), out_dir=str(tmp_path / "o")))
    assert not r.ok and "piv.window_px" in r.error


def test_read_levels(tmp_path):
    p = tmp_path / "l.csv"
    p.write_text("Video;Level_m\na.mp4;10,25\nb.MOV;9.5\n")
    assert read_levels(p) == {"a.mp4": 10.25, "a": 10.25, "b.MOV": 9.5, "b": 9.5}
    p.write_text("video,water_level_m\na.mp4,high\n")
    with pytest.raises(Exception, match="line 2.*not a number"):
        read_levels(p)
    p.write_text("file,depth\na.mp4,1\n")
    with pytest.raises(Exception, match="water_level_m"):
        read_levels(p)


@pytest.fixture(scope="module")
def three_scenes(rendered):
    """Three short demo scenes (one per preset) and their discharges from separate run_project calls."""
    from fieldtool.project.model import load_project
    from fieldtool.run.pipeline import run_project

    out = []
    for name in ("oblique", "nadir", "far_bank"):
        truth = rendered(name, duration_s=0.5, seed=11)
        q = run_project(load_project(truth.project_path)).discharge.discharge_m3s
        out.append((truth.project_path, q))
    return out


@pytest.mark.slow
def test_batch_on_local_dask_cluster_matches_single_runs(three_scenes, tmp_path):
    distributed = pytest.importorskip("distributed")
    paths = [p for p, _ in three_scenes]
    items = plan_projects(paths, out_root=tmp_path / "out", site="synthetic")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", protocol="tcp", dashboard_address=None
    ) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        with History(tmp_path / "h.sqlite") as hist:
            res = run_batch(items, history=hist, scheduler=cluster.scheduler_address)
            rows = hist.query(site="synthetic")
    assert res.executor.startswith("dask tcp://")
    assert not res.failed, [r.error for r in res.failed]
    for (_, q), r in zip(three_scenes, res.results, strict=True):
        assert r.summary["discharge_m3s"] == pytest.approx(q, rel=1e-9)
        assert (Path(r.item.out_dir) / "result.json").is_file()
    assert sorted(m.discharge_m3s for m in rows) == pytest.approx(sorted(q for _, q in three_scenes), rel=1e-9)
    assert {m.output_dir for m in rows} == {str(Path(r.item.out_dir).resolve()) for r in res.results}
    assert all(len(m.input_hash) == 64 and m.video_time for m in rows)


@pytest.mark.slow
def test_batch_folder_of_videos_with_failures(three_scenes, tmp_path, capsys):
    """Site + folder of videos on 2 local processes: a corrupt video, a video without a level and a
    level without a video fail with their reasons; the good video is run and recorded once."""
    project, q = three_scenes[0]
    sites, db = tmp_path / "sites", tmp_path / "h.sqlite"
    assert main(["site", "create", "demo", "--from", str(project), "--sites", str(sites)]) == 0
    vids = tmp_path / "videos"
    vids.mkdir()
    shutil.copy(Path(project).parent / "river.mp4", vids / "good.mp4")
    (vids / "broken.mp4").write_bytes(b"\x00\x01garbage" * 500)
    shutil.copy(Path(project).parent / "river.mp4", vids / "nolevel.mp4")
    (vids / "levels.csv").write_text("video,water_level_m\ngood.mp4,10.0\nbroken.mp4,10.0\nghost.mp4,9.0\n")
    args = [
        "batch",
        "--site",
        "demo",
        "--videos",
        str(vids),
        "--levels",
        str(vids / "levels.csv"),
        "--workers",
        "2",
        "--sites",
        str(sites),
        "--db",
        str(db),
        "--report",
    ]
    assert main(args) == 1
    out = capsys.readouterr().out
    assert "1 of 4 done" in out
    assert "ok      good.mp4: Q = " in out
    failed = {ln.split(":")[0].split()[-1]: ln for ln in out.splitlines() if ln.strip().startswith("FAILED")}
    assert set(failed) == {"broken.mp4", "nolevel.mp4", "ghost.mp4"}
    assert "broken.mp4: cannot be read as a video" in failed["broken.mp4"]
    assert "no water level for nolevel.mp4" in failed["nolevel.mp4"]
    assert "not in" in failed["ghost.mp4"]
    with History(db) as h:
        (m,) = h.query()
    assert m.site == "demo" and m.discharge_m3s == pytest.approx(q, rel=1e-9) and m.water_level_m == 10.0
    assert Path(m.output_dir, "report.html").is_file()
    # again with --skip-existing: nothing recorded twice
    assert main(args + ["--skip-existing"]) == 1
    assert "already in the history" in capsys.readouterr().err
    with History(db) as h:
        assert len(h.query()) == 1


def test_batch_cli_needs_inputs(tmp_path, capsys):
    assert main(["batch", "--db", str(tmp_path / "h.sqlite")]) == 2
    assert "nothing to run" in capsys.readouterr().err
    assert main(["batch", "--videos", str(tmp_path), "--db", str(tmp_path / "h.sqlite")]) == 2
    assert "--site" in capsys.readouterr().err
