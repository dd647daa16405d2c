"""The TUI driven by keys only (Textual Pilot) on the demo scene, cut to a short clip.

Truth: the discharge of the walk-through must equal pipeline.run_project on the same project
file; the project file on disk must hold what was typed, survive a kill mid-run, and reopen on
the step that was left.
"""

import asyncio
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from fieldtool.project.model import load_project, save_project
from fieldtool.run.pipeline import run_project
from fieldtool.tui.app import FieldToolApp
from fieldtool.tui.screens.piv import PivScreen
from fieldtool.tui.screens.results import ResultsScreen
from fieldtool.tui.screens.section import SectionScreen
from fieldtool.tui.screens.video import VideoScreen
from fieldtool.tui.steps import STEP_IDS

SIZE = (80, 24)


@pytest.fixture(scope="module")
def demo_scene(short_scene):
    """The demo ('oblique') scene, 1.2 s (36 frames) instead of 5 s: the session's short scene (never written to)."""
    return short_scene.project_path.parent


@pytest.fixture
def project_path(demo_scene, tmp_path):
    """A fresh copy of the demo project; PIV on the first 0.5 s to keep the run short."""
    dst = tmp_path / "scene"
    shutil.copytree(demo_scene, dst)
    path = dst / "project.toml"
    p = load_project(path)
    p.video.end_s = 0.5
    save_project(p, path)
    return path


async def wait_job(app, pilot, timeout=180.0):
    t0 = time.monotonic()
    while app.job is not None:
        assert time.monotonic() - t0 < timeout, "run did not finish"
        await pilot.pause(0.1)
    await pilot.pause()


async def type_into_focused(pilot, text: str):
    await pilot.press("end", "ctrl+u", *text)
    await pilot.pause()


def test_walkthrough_by_keys_gives_the_pipeline_discharge(project_path, tmp_path):
    timings = {}

    async def walk():
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            t0 = time.monotonic()
            await pilot.pause()
            for step in STEP_IDS[: STEP_IDS.index("piv")]:
                assert app.screen.STEP == step
                await pilot.press("ctrl+n")
                await pilot.pause()
            assert isinstance(app.screen, PivScreen)
            await pilot.press("ctrl+r")
            await pilot.pause()
            # the run is under way (status line shown), or already done with a result on a fast machine
            if app.job is not None:
                assert app.screen.query_one("#status").display
            else:
                assert "discharge_m3s" in app.last_job.get("piv", {}), (
                    app.last_job,
                    str(app.screen.query_one("#step-errors").render()),
                )
            await wait_job(app, pilot)
            await pilot.press("ctrl+n")
            await pilot.pause()
            assert isinstance(app.screen, SectionScreen)
            await pilot.press("ctrl+n")
            await pilot.pause()
            assert isinstance(app.screen, ResultsScreen)
            await wait_job(app, pilot)
            timings["walk"] = time.monotonic() - t0
            summary = app.session.last_result().summary
            shown = str(app.screen.query_one("#summary").render())
            assert f"{summary['discharge_m3s']:.4f} m³/s" in shown
            assert len(app.screen.query_one("#subsections").rows) == app.session.project.section.n_sub
            marks = app.session.step_marks()
            assert set(marks.values()) == {"ok"}
            # the reference: the headless pipeline on the project file the walk-through left
            ref = run_project(load_project(project_path), tmp_path / "ref").summary()
            assert summary["discharge_m3s"] == pytest.approx(ref["discharge_m3s"], rel=1e-12)
            assert summary["wetted_area_m2"] == pytest.approx(ref["wetted_area_m2"], rel=1e-12)
            drop_step = lambda d: {k: v for k, v in d.items() if k != "step"}  # noqa: E731
            assert drop_step(summary["inputs"]) == drop_step(ref["inputs"])

            # jump back with the command palette, change a PIV parameter: PIV and discharge go stale
            await pilot.press("ctrl+p", *"PIV")
            await pilot.pause(0.3)
            await pilot.press("enter")
            await pilot.pause()
            assert isinstance(app.screen, PivScreen)
            await pilot.press("tab")  # window -> overlap
            await type_into_focused(pilot, "8")
            assert app.session.project.piv.overlap_px == 8
            marks = app.session.step_marks()
            assert marks["piv"] == "stale" and marks["results"] == "stale" and marks["section"] == "ok"

    asyncio.run(walk())
    print(f"\nPilot walk-through (demo scene, first 0.5 s = 15 frames): {timings['walk']:.1f} s")


def test_invalid_entries_show_messages_and_block_next(project_path):
    async def run():
        p = load_project(project_path)
        p.step = "video"
        save_project(p, project_path)
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            assert isinstance(app.screen, VideoScreen)
            await pilot.press("tab")  # video.path -> video.start_s
            await type_into_focused(pilot, "abc")
            row = app.screen.query_one("#f-video-start_s")
            assert "video.start_s: 'abc' is not a number" in row.error
            assert row.query_one(".field-error").display
            await pilot.press("ctrl+n")
            await pilot.pause()
            assert isinstance(app.screen, VideoScreen)  # blocked
            assert "is not a number" in str(app.screen.query_one("#step-errors").render())
            assert load_project(project_path).video.start_s == 0.0  # the bad text never reaches the file

            await type_into_focused(pilot, "0.6")  # parses, but after video.end_s = 0.5
            assert load_project(project_path).video.start_s == 0.6  # kept: nothing typed is lost
            assert "must be after the start" in app.screen.query_one("#f-video-end_s").error
            await pilot.press("ctrl+n")
            await pilot.pause()
            assert isinstance(app.screen, VideoScreen)

            # the refused "next" put the cursor in the field at fault
            assert app.focused is app.screen.query_one("#f-video-end_s Input")
            await type_into_focused(pilot, "0.9")
            assert app.screen.query_one("#f-video-end_s").error is None
            await pilot.press("ctrl+n")
            await pilot.pause()
            assert app.screen.STEP == "calibration"

    asyncio.run(run())


def test_cancel_during_piv_keeps_the_ui_and_writes_no_result(project_path, monkeypatch):
    import fieldtool.run.frames as frames_mod

    streamed = frames_mod.working_frames

    def slow_frames(*args, **kwargs):  # 50 ms a frame: the run outlasts the key press, whatever the CPU
        for item in streamed(*args, **kwargs):
            time.sleep(0.05)
            yield item

    monkeypatch.setattr(frames_mod, "working_frames", slow_frames)

    async def run():
        p = load_project(project_path)
        p.step = "piv"
        p.video.end_s = None  # the whole 1.2 s clip
        save_project(p, project_path)
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("ctrl+r")
            t0 = time.monotonic()
            while app.job is not None and app.job.done < 1:
                assert time.monotonic() - t0 < 60
                await pilot.pause(0.02)
            assert app.job is not None, "the run ended before it could be cancelled"
            await pilot.press("escape")
            await wait_job(app, pilot)
            assert "cancelled" in app.last_job["piv"]
            label = str(app.screen.query_one("#status").render())
            assert "cancelled" in label
            await pilot.press("ctrl+n")  # still responsive
            await pilot.pause()
            assert isinstance(app.screen, SectionScreen)
        assert not (project_path.parent / "out" / "result.json").exists()
        assert load_project(project_path).step == "section"

    asyncio.run(run())


def test_reopening_restores_the_step_and_values(project_path):
    async def first():
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            for _ in range(STEP_IDS.index("piv")):
                await pilot.press("ctrl+n")
                await pilot.pause()
            assert isinstance(app.screen, PivScreen)
            await type_into_focused(pilot, "24")  # piv.window_px
            await pilot.press("ctrl+q")
            await pilot.pause()

    async def second():
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            assert isinstance(app.screen, PivScreen)
            assert app.screen.query_one("#f-piv-window_px Input").value == "24"
            assert app.screen.query_one("#f-piv-overlap_px Input").value == "16"

    asyncio.run(first())
    p = load_project(project_path)
    assert p.step == "piv" and p.piv.window_px == 24
    asyncio.run(second())


CRASH_SCRIPT = textwrap.dedent("""
    import asyncio, sys, time
    import fieldtool.run.frames as frames_mod
    from fieldtool.tui.app import FieldToolApp

    streamed = frames_mod.working_frames

    def slow_frames(*args, **kwargs):  # 50 ms a frame: the run is still going when the process is killed
        for item in streamed(*args, **kwargs):
            time.sleep(0.05)
            yield item

    frames_mod.working_frames = slow_frames

    async def main():
        app = FieldToolApp(sys.argv[1])
        async with app.run_test(size=(80, 24)) as pilot:
            await pilot.pause()
            await pilot.press("end", "ctrl+u", "2", "4")  # piv.window_px = 24
            await pilot.pause()
            await pilot.press("ctrl+r")
            while app.job is None or app.job.done < 1:
                await pilot.pause(0.02)
            open(sys.argv[2], "w").write("running")
            while True:
                await pilot.pause(0.05)

    asyncio.run(main())
""")


def test_kill_mid_piv_leaves_a_valid_project_file(project_path, tmp_path):
    p = load_project(project_path)
    p.step = "piv"
    p.video.end_s = None
    save_project(p, project_path)
    script = tmp_path / "crash.py"
    script.write_text(CRASH_SCRIPT)
    marker = tmp_path / "running"
    proc = subprocess.Popen(
        [sys.executable, str(script), str(project_path), str(marker)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        t0 = time.monotonic()
        while not marker.exists():
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() - t0 < 90
            time.sleep(0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    q = load_project(project_path)  # parses: the file was never half-written
    assert q.piv.window_px == 24 and q.step == "piv"
    assert q.video.path == p.video.path and q.ortho.gcp_px == p.ortho.gcp_px
    leftovers = [f.name for f in Path(project_path).parent.iterdir() if f.name.endswith(".tmp")]
    assert leftovers == []


def _slow_frames(monkeypatch, delay=0.05):
    """50 ms a frame: a run outlasts a few key presses and screen reads, whatever the CPU."""
    import fieldtool.run.frames as frames_mod

    streamed = frames_mod.working_frames

    def slow_frames(*args, **kwargs):
        for item in streamed(*args, **kwargs):
            time.sleep(delay)
            yield item

    monkeypatch.setattr(frames_mod, "working_frames", slow_frames)


def screen_lines(app) -> list[str]:
    return [strip.text for strip in app.screen._compositor.render_strips()]


def test_piv_progress_line_is_on_screen_at_80x24(project_path, monkeypatch):
    """Defect: the PIV progress bar was below the fold (only "esc Cancel" in the footer showed a run).
    The status line above the footer shows the job, its progress, elapsed/remaining time and the
    cancel key, on the 80 x 24 screen, and stays when the operator moves to another step."""
    _slow_frames(monkeypatch, delay=0.2)

    async def run():
        p = load_project(project_path)
        p.step = "piv"
        save_project(p, project_path)
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("ctrl+r")
            t0 = time.monotonic()
            while app.job is None or app.job.done < 2:
                assert time.monotonic() - t0 < 60
                await pilot.pause(0.05)
            await pilot.pause(0.3)
            lines = screen_lines(app)
            assert len(lines) == SIZE[1]
            status = lines[-2]  # the line above the footer
            assert re.search(
                r"▶ PIV and discharge: .* \d+/\d+ · \d+:\d\d elapsed · (\d+:\d\d|--:--) left · esc cancels", status
            ), status
            await pilot.press("ctrl+b")  # another step: the run is still shown
            await pilot.pause(0.3)
            assert "▶ PIV and discharge" in screen_lines(app)[-2]
            await pilot.press("escape")
            await wait_job(app, pilot)
            last = screen_lines(app)[-2]  # how the run ended (cancelled, or done when the machine was quicker)
            assert "cancelled" in last or "done in" in last, last

    asyncio.run(run())


def test_piv_without_a_section_is_kept_when_quitting(project_path, tmp_path):
    """Defect: a finished PIV was lost when the user quit before a section existed. The PIV-only run
    saves the field at once (out/tui_piv, the PIV cache's format and key): a new session finds it (PIV
    marked done, its figures shown). The discharge run does not take it for its own (its PIV has stages
    the PIV-only run does not repeat): its discharge is that of a fresh run."""
    section = load_project(project_path).section.points_px

    async def first():
        p = load_project(project_path)
        p.step = "piv"
        p.section.points_px = []
        save_project(p, project_path)
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("ctrl+r")
            await pilot.pause()
            await wait_job(app, pilot)
            assert "stats" in app.last_job["piv"], app.last_job
            await pilot.press("ctrl+q")

    asyncio.run(first())
    assert (project_path.parent / "out" / "tui_piv" / "piv_cache.npz").is_file()
    from fieldtool.tui.session import Session

    s = Session(project_path)
    assert s.piv_state() == "current"
    assert s.step_marks()["piv"] == "ok"
    assert s.piv_preview["stats"]["pairs"] > 0
    p = load_project(project_path)
    ref = load_project(project_path)
    p.section.points_px = ref.section.points_px = section
    res = run_project(p, project_path.parent / "out")
    assert not res.piv_reused
    fresh = run_project(ref, tmp_path / "fresh")
    assert not fresh.piv_reused
    assert res.discharge.discharge_m3s == pytest.approx(fresh.discharge.discharge_m3s, rel=1e-12)


def test_results_screen_says_it_is_computing(project_path, monkeypatch):
    """Defect: the results screen said "no result yet: ctrl+r computes" while it was computing."""
    _slow_frames(monkeypatch)

    async def run():
        p = load_project(project_path)
        p.step = "results"
        save_project(p, project_path)
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            assert app.job is not None  # computing on arrival
            text = "\n".join(screen_lines(app))
            assert "computing the discharge" in text and "no result yet" not in text
            await wait_job(app, pilot)
            await pilot.pause(0.3)
            assert "computing" not in "\n".join(screen_lines(app))
            assert f"{app.session.last_result().summary['discharge_m3s']:.4f}" in "\n".join(screen_lines(app))

    asyncio.run(run())


def test_a_failed_save_is_said_in_place_and_kept_for_the_next_save(project_path, monkeypatch):
    """Disk full (or a read-only folder) while editing: the TUI says NOT SAVED on its status line and title,
    keeps the entry in memory, and the next successful save writes every entry since the last one."""
    import errno

    from fieldtool.tui.session import Session

    p = load_project(project_path)
    p.step = "piv"
    save_project(p, project_path)
    real_save = Session.save
    state = {"fail": True}

    def flaky_save(self):
        if state["fail"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_save(self)

    monkeypatch.setattr(Session, "save", flaky_save)

    async def run():
        app = FieldToolApp(project_path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("end", "ctrl+u", "2", "4")  # piv.window_px = 24, not written
            await pilot.pause()
            assert app.status[1] and app.status[0].startswith("NOT SAVED")
            assert "No space left on device" in app.status[0]
            assert "NOT SAVED" in "\n".join(screen_lines(app))
            assert app.session.project.piv.window_px == 24
            assert load_project(project_path).piv.window_px != 24
            state["fail"] = False
            await pilot.press("tab", "end", "ctrl+u", "8")  # piv.overlap_px = 8: this save writes both
            await pilot.pause()
            assert not app.status[1]
        saved = load_project(project_path)
        assert (saved.piv.window_px, saved.piv.overlap_px) == (24, 8)

    asyncio.run(run())
