"""Outputs replaced as a unit, strict JSON, batch output clashes, picks loaded exactly."""

import json
import math

import pytest

from fieldtool.errors import ParameterError
from fieldtool.run.outdir import Staging, strict_json


def test_staging_swaps_and_carries(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "result.json").write_text(json.dumps({"files": {"a": "a.png", "result": "result.json"}}))
    (out / "a.png").write_text("old a")  # listed by the old run, not written by the new one: stale
    (out / "piv_cache.npz").write_text("cache")  # not listed: carried over
    (out / "notes.txt").write_text("the user's")
    st = Staging(out)
    assert st.path != out and st.path.parent == out.parent
    (st.path / "result.json").write_text(json.dumps({"files": {"b": "b.png"}}))
    (st.path / "b.png").write_text("new b")
    assert (out / "a.png").read_text() == "old a"  # nothing changed before the commit
    st.commit()
    assert sorted(p.name for p in out.iterdir()) == ["b.png", "notes.txt", "piv_cache.npz", "result.json"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_staging_abort_leaves_the_old_run(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "result.json").write_text("{}")
    st = Staging(out)
    (st.path / "result.json").write_text('{"new": 1}')
    st.abort()
    assert (out / "result.json").read_text() == "{}"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_killed_run_leaves_previous_run_intact(short_scene, tmp_path, monkeypatch):
    """A failure while the outputs are written (here: the plots) leaves the previous run as it was."""
    from fieldtool.project.model import load_project
    from fieldtool.run import pipeline

    out = tmp_path / "out"
    proj = load_project(short_scene.project_path)
    pipeline.run_project(proj, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    import fieldtool.plots.discharge as plots

    def boom(*a, **k):
        raise KeyboardInterrupt  # as a kill would, midway through the outputs

    monkeypatch.setattr(plots, "plot_section", boom)
    proj.section.n_sub = 7
    with pytest.raises(KeyboardInterrupt):
        pipeline.run_project(proj, out)
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_strict_json_names_non_finite():
    w: list[str] = []
    d = strict_json({"discharge_m3s": math.inf, "x": [1.0, math.nan]}, w)
    assert d == {"discharge_m3s": None, "x": [1.0, None]}
    assert len(w) == 2 and "discharge_m3s" in w[0]
    json.dumps(d, allow_nan=False)


def test_batch_refuses_shared_output(tmp_path):
    from fieldtool.records.batch import check_distinct_outputs, plan_projects

    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text(""), b.write_text("")
    with pytest.raises(ParameterError, match="a.toml and .*b.toml both write into"):
        check_distinct_outputs(plan_projects([a, b]))


def test_picks_loaded_exactly():
    from fieldtool.viewer.picks import MODES

    st = MODES["gcp"].make()
    v = [[1079.753, 651.8051], [1.0, 2.0], [3.333333, 4.0], [5.0, 6.0]]
    st.load(v)
    assert st.value() == v  # choosing a mode does not round existing picks
