"""The velocity figures are drawn in a forked child during the Monte Carlo; the parent draws any it lacks."""

import os

import pytest

from fieldtool.pipeline import run_project
from fieldtool.plots import prerender
from fieldtool.project import load_project

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no os.fork here: the parent draws every figure")
def test_figures_come_from_the_forked_child(scene, monkeypatch):
    drawn_in = {}
    real_collect = prerender.Prerender._collect

    def collect(self):
        pid = self._pid
        real_collect(self)
        if pid is not None:  # the first call waits for the child; later ones find it reaped
            drawn_in.update({n: (pid, n in self._png) for n in prerender.FORKED})

    monkeypatch.setattr(prerender.Prerender, "_collect", collect)
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    assert drawn_in and all(pid and pid != os.getpid() and got for pid, got in drawn_in.values())
    for name in prerender.FORKED:
        data = (scene / "out" / name).read_bytes()
        assert data.startswith(PNG) and len(data) > 10_000
    assert {"vectors_png", "rectified_png", "section_png"} <= set(res.files)
    assert not [p for p in os.listdir(os.path.dirname(res.out_dir)) if p.startswith("fieldtool-fig-")]


def test_a_child_that_fails_leaves_its_figures_to_the_parent(scene, monkeypatch):
    from fieldtool.plots import discharge as plots

    calls = []
    real = plots.plot_section

    def failing_in_child(path, cs, result):
        if os.getpid() != parent:
            raise RuntimeError("child fails")
        calls.append(path.name)
        return real(path, cs, result)

    parent = os.getpid()
    monkeypatch.setattr(plots, "plot_section", failing_in_child)
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    assert (scene / "out" / "section.png").read_bytes().startswith(PNG)
    assert (scene / "out" / "vectors.png").read_bytes().startswith(PNG)
    if hasattr(os, "fork"):
        assert calls == ["section.png"]  # the child failed: the parent drew it
    assert "section_png" in res.files
