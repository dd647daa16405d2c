"""rerun stream of a run: saved to an .rrd file, read back with rerun's RrdReader."""

import argparse
import json

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from fieldtool.errors import ParameterError
from fieldtool.project.model import load_project
from fieldtool.run.pipeline import run_project
from fieldtool.viewer.rerun_log import RerunObserver, _map_arrow_s, observer_from_args

EXPECTED = {
    "/frames/input",
    "/frames/filtered",
    "/frames/input/pair_vectors",
    "/frames/input/mean_field",
    "/frames/input/section",
    "/map/mean_field",
    "/map/section/subsections",
    "/section/surface_velocity_ms",
    "/section/discharge_m3s",
    "/piv/valid_fraction",
    "/discharge/pair_m3s",
    "/discharge/running_m3s",
    "/discharge/final_m3s",
    "/log",
    "/map/background",
    "/section/profile/velocity",
    "/section/profile/band",
}


def _column(rows, name):
    return [v for rb in rows if name in rb.schema.names for v in rb.column(name).to_pylist()]


def _read(path):
    out = {}
    for ch in RrdReader(path).stream():
        out.setdefault(ch.entity_path, []).append(ch.to_record_batch())
    return out


@pytest.fixture(scope="module")
def logged_run(short_scene, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("rerun_run")
    project = load_project(short_scene.project_path)
    project.video.end_s = 0.5
    args = argparse.Namespace(rerun="save", rerun_path=None, rerun_url=None)
    obs = observer_from_args(project, args, tmp / "out")
    result = run_project(project, tmp / "out", observer=obs)
    return result, tmp / "out", _read(tmp / "out" / "run.rrd")


def test_the_recording_holds_every_entity(logged_run):
    result, out, ent = logged_run
    assert EXPECTED <= set(ent), sorted(EXPECTED - set(ent))
    assert not [w for w in result.warnings if "rerun" in w]


def test_vector_counts_match_the_fields(logged_run):
    result, out, ent = logged_run
    with np.load(out / "mean_field.npz") as z:
        ok = z["valid"] & np.isfinite(z["u_px_s"]) & np.isfinite(z["v_px_s"])
        U, V = z["U_ms"][ok], z["V_ms"][ok]
        z_x, z_y = z["x_px"], z["y_px"]
    mean = _column(ent["/frames/input/mean_field"], "Arrows2D:vectors")
    assert len(mean) == 1 and len(mean[0]) == int(ok.sum()) > 0
    world = np.array(_column(ent["/map/mean_field"], "Arrows2D:vectors")[0])
    XY = result.mapping.image_to_world(np.c_[z_x[ok], z_y[ok]])
    s = _map_arrow_s(XY, U, V)
    assert 0 < s < 10
    np.testing.assert_allclose(world, np.c_[U, -V] * s, rtol=1e-5, atol=1e-6)  # m/s (north up) x s
    pairs = _column(ent["/frames/input/pair_vectors"], "Arrows2D:vectors")
    p = result.piv
    expected = [int(np.sum(np.isfinite(p.u_pairs[k]) & np.isfinite(p.v_pairs[k]))) for k in range(len(p.u_pairs))]
    assert [len(a) for a in pairs] == expected
    frac = np.ravel(_column(ent["/piv/valid_fraction"], "Scalars:scalars"))
    np.testing.assert_allclose(frac, np.array(expected) / p.u_pairs[0].size, rtol=1e-6)


def test_discharge_scalars(logged_run):
    result, out, ent = logged_run
    q = json.loads((out / "result.json").read_text())["discharge_m3s"]
    final = np.ravel(_column(ent["/discharge/final_m3s"], "Scalars:scalars"))
    assert final.tolist() == pytest.approx([q, q], rel=1e-9)  # drawn across the clip's span
    pair_q = np.ravel(_column(ent["/discharge/pair_m3s"], "Scalars:scalars"))
    fin = result.q_pairs[np.isfinite(result.q_pairs)]
    np.testing.assert_allclose(pair_q, fin)
    running = np.ravel(_column(ent["/discharge/running_m3s"], "Scalars:scalars"))
    assert running[-1] == pytest.approx(np.median(fin))
    ns = [
        v
        for rb in ent["/discharge/pair_m3s"]
        if "time" in rb.schema.names
        for v in rb.column("time").cast(pa.int64()).to_pylist()
    ]
    t_pairs = np.asarray(result.piv.t_pairs)[np.isfinite(result.q_pairs)]
    np.testing.assert_allclose(np.array(ns) / 1e9, t_pairs, atol=1e-6)  # on the clip's time timeline (s)


def test_observer_from_args_modes(tmp_path):
    project = load_project_stub()
    none = argparse.Namespace(rerun=None, rerun_path=None, rerun_url=None)
    assert observer_from_args(project, none, tmp_path) is None  # off by default
    project.rerun.mode = "save"
    obs = observer_from_args(project, none, tmp_path / "out")
    assert obs.path == tmp_path / "out" / "run.rrd"
    obs.close()
    flag = argparse.Namespace(rerun="save", rerun_path=str(tmp_path / "x.rrd"), rerun_url=None)
    obs = observer_from_args(project, flag, tmp_path / "out")  # the flags override the project
    assert obs.path == tmp_path / "x.rrd"
    obs.close()
    bad = argparse.Namespace(rerun="connect", rerun_path=None, rerun_url="http://host:9876")
    with pytest.raises(ParameterError, match="--rerun-url"):
        observer_from_args(project, bad, tmp_path)
    project.rerun.mode = "bogus"
    with pytest.raises(ParameterError, match="rerun.mode"):
        observer_from_args(project, none, tmp_path)


def load_project_stub():
    from fieldtool.project.model import Project

    return Project()


def test_a_failing_logger_becomes_a_warning_and_the_run_goes_on(short_scene, tmp_path):
    class Broken:
        def __getattr__(self, name):
            def fail(*a, **k):
                raise ConnectionError("viewer went away")

            return fail

    project = load_project(short_scene.project_path)
    project.video.end_s = 0.3
    obs = RerunObserver("save", recording=Broken())
    result = run_project(project, None, observer=obs)
    assert np.isfinite(result.discharge.discharge_m3s)
    assert any("rerun logging stopped" in w and "viewer went away" in w for w in result.warnings)


@pytest.mark.slow
def test_unreachable_viewer_is_a_warning(tmp_path):
    obs = RerunObserver("connect", url="rerun+http://127.0.0.1:9/proxy")
    obs.pair(0, 0.1, np.zeros((2, 2)), np.zeros((2, 2)), np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2), bool))
    obs.close(timeout_s=8.0)
    assert any("did not get everything" in w for w in obs.warnings), obs.warnings


@pytest.mark.parametrize("bad", ["/some/file", "../../x.rrd", ".", "..", "sub/../../x.rrd", "~/x.rrd"])
def test_rerun_path_is_confined_to_the_output_folder(short_scene, tmp_path, capsys, bad):
    """A project's rerun.path never writes outside the output folder: exit 2 naming the key, nothing written."""
    import tomli_w

    from fieldtool.cli.main import main
    from fieldtool.project.model import project_to_dict

    project = load_project(short_scene.project_path)
    project.rerun.mode, project.rerun.path = "save", bad
    d = project_to_dict(project)
    d["rerun"]["path"] = bad
    for table in ("video", "cross_section"):
        if d[table].get("path"):
            d[table]["path"] = str(project.resolve(d[table]["path"]))
    path = tmp_path / "p" / "project.toml"
    path.parent.mkdir()
    path.write_text(tomli_w.dumps(d))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(["run", str(path), "--out", str(tmp_path / "p" / "out" / "run1"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "rerun.path" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written anywhere
    assert not list(tmp_path.rglob("*.rrd"))


def test_rerun_path_inside_the_output_folder_is_accepted(tmp_path):
    from fieldtool.viewer.rerun_log import confined_rrd_path

    assert confined_rrd_path("run.rrd", tmp_path) == tmp_path.resolve() / "run.rrd"
    assert confined_rrd_path("live/a.rrd", tmp_path) == tmp_path.resolve() / "live" / "a.rrd"
    (tmp_path / "link").symlink_to("/tmp")
    with pytest.raises(ParameterError, match="rerun.path"):
        confined_rrd_path("link/x.rrd", tmp_path)


def test_the_recording_holds_the_blueprint_and_named_series(logged_run):
    """The .rrd carries the layout (a blueprint store with the four named views) and every discharge
    series has a name that says what it is."""
    result, out, ent = logged_run
    reader = RrdReader(out / "run.rrd")
    (bp,) = reader.blueprints()
    names = []
    for ch in reader.stream(store=bp):
        rb = ch.to_record_batch()
        for col in rb.schema.names:
            if col.endswith("display_name"):
                names += [v for v in rb.column(col).to_pylist() if v]
    names = [n[0] if isinstance(n, list) else n for n in names]
    for want in (
        "Current frame and live vectors",
        "Rectified map and mean field",
        "Section: surface velocity",
        "Discharge over time",
    ):
        assert any(want in n for n in names), (want, names)
    series = {}
    for path, rows in ent.items():
        for rb in rows:
            for col in rb.schema.names:
                if col.endswith(":names") and path.startswith("/discharge/"):
                    series[path] = rb.column(col).to_pylist()[0][0]
    assert series["/discharge/pair_m3s"].startswith("per-pair Q")
    assert series["/discharge/running_m3s"].startswith("running estimate")
    assert series["/discharge/final_m3s"].startswith("final Q")
    assert "95 %" in series["/discharge/final_ci95_lo_m3s"] and "95 %" in series["/discharge/final_ci95_hi_m3s"]
    assert len(set(series.values())) == len(series)


def test_interval_and_quality_lines_follow_the_result_keys():
    """Q's interval and the grade are read from helper quality's keys, and absent until they exist."""
    from types import SimpleNamespace

    from fieldtool.viewer.rerun_log import _interval, _quality_line

    summary = {}
    res = SimpleNamespace(summary=lambda: summary, discharge=SimpleNamespace(discharge_m3s=10.0))
    assert _interval(res) is None and _quality_line(res) is None
    summary["uncertainty"] = {"ci95_m3s": [9.5, 10.6]}
    assert _interval(res) == (9.5, 10.6)
    summary["discharge_ci95_m3s"] = [9.0, 11.0]
    summary["quality"] = {"grade": "doubtful", "reasons": [{"code": "x", "message": "few valid vectors"}]}
    assert _interval(res) == (9.0, 11.0)
    text, level = _quality_line(res)
    assert level == "WARN" and "9.000 - 11.000" in text and "doubtful" in text and "few valid vectors" in text
    summary["discharge_ci95_m3s"] = [None, 11.0]
    summary.pop("uncertainty")
    assert _interval(res) is None
