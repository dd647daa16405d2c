"""The figures are drawn by the figure process (plots.prerender); the parent draws any it lacks."""

import io
import os
import pickle
import tempfile
import time

import pytest

from fieldtool.plots import discharge as plots
from fieldtool.plots import prerender, report_figures
from fieldtool.project.model import load_project
from fieldtool.run.pipeline import run_project

PNG = b"\x89PNG\r\n\x1a\n"
FIGURES = ("vectors.png", "rectified.png", "section.png", "profile.png", "gcp.png", "water_level.png")

needs_fork = pytest.mark.skipif(not prerender.can_fork(), reason="no os.fork here: the parent draws every figure")


@pytest.fixture
def own_tmp(monkeypatch, tmp_path):
    """No figure process left from another test, and the temporary folders in this test's own place."""
    if prerender._waiting is not None:
        prerender._waiting.stop()
        prerender._waiting = None
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    yield tmp
    if prerender._waiting is not None:
        prerender._waiting.stop()
        prerender._waiting = None


def _check_outputs(out, res):
    for name in FIGURES:
        data = (out / name).read_bytes()
        assert data.startswith(PNG) and len(data) > 10_000, name
    assert (out / "section_profile.csv").read_text().startswith("station_m,")
    assert {
        "vectors_png",
        "rectified_png",
        "section_png",
        "profile_png",
        "gcp_png",
        "water_level_png",
        "section_profile",
    } <= set(res.files)


@needs_fork
def test_every_figure_comes_from_the_figure_process(scene, own_tmp, monkeypatch):
    parent = os.getpid()

    def only_in_child(real):
        def draw(*a, **k):
            assert os.getpid() != parent, f"{real.__name__} drawn in the parent"
            return real(*a, **k)

        return draw

    for mod, name in (
        (plots, "plot_vectors"),
        (plots, "plot_rectified"),
        (plots, "plot_section"),
        (report_figures, "write_profile"),
        (report_figures, "write_gcp"),
    ):
        monkeypatch.setattr(mod, name, only_in_child(getattr(mod, name)))
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    _check_outputs(scene / "out", res)
    assert not res.warnings or not any("not written" in w for w in res.warnings)
    assert list(own_tmp.iterdir()) == []  # the process' folder is gone with it


def _modules(blob: bytes) -> set[str]:
    """The modules whose classes or functions a pickle names (what unpickling it imports)."""
    found: set[str] = set()

    class Names(pickle.Unpickler):
        def find_class(self, module, name):
            found.add(module)
            return super().find_class(module, name)

    Names(io.BytesIO(blob)).load()
    return found


@needs_fork
def test_the_velocity_figures_jobs_import_nothing_the_warm_job_did_not(scene, own_tmp, monkeypatch):
    """Unpickling the velocity figures' job at the run's end imported the PIV's and the discharge's modules (0.14
    s at 720p, on the run's critical path); the warm job, sent with the input figures, imports them meanwhile."""
    jobs: list[tuple[str, tuple]] = []
    real = prerender._Process.submit

    def submit(self, kind, args):
        jobs.append((kind, args))
        return real(self, kind, args)

    monkeypatch.setattr(prerender._Process, "submit", submit)
    run_project(load_project(scene / "project.toml"), scene / "out")
    kinds = [k for k, _ in jobs]
    assert kinds == ["inputs", "warm", "field", "results"]  # the field's figure before STIV's analysis ends
    inputs, warm = _modules(pickle.dumps(jobs[0][1])), set(jobs[1][1])
    later = _modules(pickle.dumps(jobs[2][1])) | _modules(pickle.dumps(jobs[3][1]))
    assert warm and all(m.startswith("fieldtool.") for m in warm)
    needed = {m for m in later if m.startswith("fieldtool.")}
    assert needed - inputs, "the test sees nothing the warm job is for"
    assert needed <= inputs | warm, needed - inputs - warm


@needs_fork
def test_a_figure_that_fails_in_the_process_is_drawn_by_the_parent(scene, own_tmp, monkeypatch):
    calls = []
    real = plots.plot_section
    parent = os.getpid()

    def failing_in_child(path, cs, result):
        if os.getpid() != parent:
            raise RuntimeError("fails in the figure process")
        calls.append(path.name)
        return real(path, cs, result)

    monkeypatch.setattr(plots, "plot_section", failing_in_child)
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    _check_outputs(scene / "out", res)
    assert calls == ["section.png"]  # only the failed one was drawn again


@needs_fork
def test_a_process_that_dies_leaves_every_figure_to_the_parent(scene, own_tmp, monkeypatch):
    def dies(*_):
        os._exit(3)

    monkeypatch.setattr(prerender, "_serve", dies)
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    _check_outputs(scene / "out", res)
    assert list(own_tmp.iterdir()) == []


@needs_fork
def test_a_process_that_hangs_is_killed_after_the_timeout(scene, own_tmp, monkeypatch):
    monkeypatch.setattr(prerender, "TIMEOUT_S", 0.5)
    monkeypatch.setattr(prerender, "_serve", lambda *_: time.sleep(60))
    t0 = time.monotonic()
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    _check_outputs(scene / "out", res)
    assert time.monotonic() - t0 < 40  # one timeout, then the parent draws (not 60 s of waiting)
    assert list(own_tmp.iterdir()) == []


@needs_fork
def test_a_timeout_kills_the_process_and_the_child_drawing_for_it(scene, own_tmp, monkeypatch, tmp_path):
    """The velocity figures are split over the figure process and a child of it: when that child hangs, the
    timeout ends both (one process group), and the run draws the figures itself."""
    parent = os.getpid()
    pid_file = tmp_path / "hung.pid"
    real = plots.plot_vectors

    def hangs_outside_the_run(*a, **k):
        if os.getpid() != parent:
            pid_file.write_text(str(os.getpid()))
            time.sleep(120)
        return real(*a, **k)

    real_answer = prerender._Process.answer

    def answer_once_hung(self, k):
        """The input figures (and matplotlib's import) get the default timeout; once the velocity figures are
        handed over, wait for their child to hang, then time the wait out after a second."""
        if self.n_jobs >= 2:
            t0 = time.monotonic()
            while not pid_file.exists() and time.monotonic() - t0 < 60:
                time.sleep(0.01)
            monkeypatch.setattr(prerender, "TIMEOUT_S", 1.0)
        return real_answer(self, k)

    monkeypatch.setattr(plots, "plot_vectors", hangs_outside_the_run)
    monkeypatch.setattr(prerender._Process, "answer", answer_once_hung)
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    _check_outputs(scene / "out", res)
    hung = int(pid_file.read_text())
    time.sleep(0.2)
    try:
        with open(f"/proc/{hung}/stat") as fh:
            assert fh.read().split(") ")[1][0] == "Z"  # killed, not yet reaped by init
    except FileNotFoundError:
        pass  # killed and reaped


@needs_fork
def test_a_waiting_process_ends_when_its_parent_closes_it(own_tmp):
    prerender.start()
    proc = prerender._waiting
    assert proc is not None and proc.alive
    prerender.start()  # one waits at a time
    assert prerender._waiting is proc
    proc.stop()
    with pytest.raises(ChildProcessError):
        os.waitpid(proc.pid, os.WNOHANG)  # reaped
    assert list(own_tmp.iterdir()) == []


@needs_fork
def test_a_run_cancelled_during_the_piv_ends_its_figure_process(scene, own_tmp, monkeypatch):
    """A cancelled (or failing) run must not leave its figure process waiting: a TUI session runs many."""
    from fieldtool.errors import Cancelled

    started = []
    real_init = prerender.Prerender.__init__

    def init(self, *a, **k):
        real_init(self, *a, **k)
        started.append(self._proc)

    monkeypatch.setattr(prerender.Prerender, "__init__", init)
    calls = {"n": 0}

    def cancel():
        calls["n"] += 1
        return calls["n"] > 5  # a few frames in

    with pytest.raises(Cancelled):
        run_project(load_project(scene / "project.toml"), scene / "out", cancel=cancel)
    assert len(started) == 1 and started[0] is not None
    assert not started[0].alive
    with pytest.raises(ChildProcessError):
        os.waitpid(started[0].pid, os.WNOHANG)  # reaped
    assert list(own_tmp.iterdir()) == []


def test_without_fork_the_parent_draws_everything(scene, own_tmp, monkeypatch):
    monkeypatch.setattr(prerender, "can_fork", lambda: False)
    res = run_project(load_project(scene / "project.toml"), scene / "out")
    _check_outputs(scene / "out", res)
    assert prerender._waiting is None


@needs_fork
def test_the_run_process_never_imports_matplotlib(scene):
    """matplotlib (about 0.5 s of import) belongs to the figure process: the run's own process leaves it alone
    when every figure came from there."""
    import subprocess
    import sys

    code = (
        "import sys; from fieldtool.cli.main import main; rc = main(['run', sys.argv[1], '--out', sys.argv[2], "
        "'--quiet']); print('matplotlib' in sys.modules, rc)"
    )
    r = subprocess.run(
        [sys.executable, "-c", code, str(scene / "project.toml"), str(scene / "out")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.stdout.strip().splitlines()[-1] == "False 0", r.stdout + r.stderr
    for name in FIGURES:
        assert (scene / "out" / name).read_bytes().startswith(PNG)


def test_the_figure_process_unpickles_the_results_without_scipy():
    """The figure process imports the modules whose classes the velocity figures' jobs hold (the warm job) and the
    plotting modules; none of them imports SciPy (0.25 s of CPU there: piv_engine imports scipy.fft on first use)."""
    import subprocess
    import sys

    from fieldtool.processing.discharge import DischargeResult
    from fieldtool.processing.piv import PivResult
    from fieldtool.processing.piv_engine import PivParams

    modules = sorted({c.__module__ for c in (PivResult, DischargeResult, PivParams)})
    modules += ["fieldtool.plots.discharge", "fieldtool.plots.report_figures", "fieldtool.plots.water_level"]
    code = "import importlib, sys; [importlib.import_module(m) for m in sys.argv[1:]]; print('scipy' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code, *modules], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "False", r.stdout + r.stderr
