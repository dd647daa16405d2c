"""`fieldtool tui`: the whole measurement, keyboard only, one screen per step (thesis fig. 9.1).

The app is small on purpose: it opens the session (project file), switches between the step
screens, runs long work in one worker thread at a time (progress, elapsed/remaining, escape
cancels) and relays picks from the viewer. Everything else lives in screens/ and widgets/.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from textual.app import App, SystemCommand
from textual.screen import Screen
from textual.worker import Worker, WorkerState

from fieldtool.errors import FieldToolError
from fieldtool.project.model import project_from_dict, project_to_dict
from fieldtool.project.sync import Conflict, SaveResult, adopt, put_mine_back
from fieldtool.tui import keys
from fieldtool.tui.jobs import Job, describe_error
from fieldtool.tui.screens.base import StepScreen
from fieldtool.tui.screens.calibration import CalibrationScreen
from fieldtool.tui.screens.conflict import ConflictScreen
from fieldtool.tui.screens.cross_section import CrossSectionScreen
from fieldtool.tui.screens.filters import FiltersScreen
from fieldtool.tui.screens.ortho import OrthoScreen
from fieldtool.tui.screens.piv import PivScreen
from fieldtool.tui.screens.results import ResultsScreen
from fieldtool.tui.screens.roi import RoiScreen
from fieldtool.tui.screens.section import SectionScreen
from fieldtool.tui.screens.video import VideoScreen
from fieldtool.tui.screens.water_level import WaterLevelScreen
from fieldtool.tui.session import Session, open_session
from fieldtool.tui.steps import STEP_IDS, STEPS
from fieldtool.tui.viewer_link import ssh_line
from fieldtool.viewer.picks import MODES
from fieldtool.viewer.registry import RunningViewer, running_viewer

if TYPE_CHECKING:  # viser is imported only when the viewer is opened
    from fieldtool.viewer.server import ViewerHandle

SCREENS_BY_STEP: dict[str, type[StepScreen]] = {
    s.STEP: s
    for s in (
        CrossSectionScreen,
        VideoScreen,
        CalibrationScreen,
        OrthoScreen,
        WaterLevelScreen,
        RoiScreen,
        FiltersScreen,
        PivScreen,
        SectionScreen,
        ResultsScreen,
    )
}
assert tuple(SCREENS_BY_STEP) == STEP_IDS


WATCH_S = 0.5  # how often the project file is looked at for another program's change (one stat)


class FieldToolApp(App):
    """The TUI on one project file (created when missing)."""

    CSS_PATH = "app.tcss"
    TITLE = "fieldtool"
    BINDINGS = keys.APP

    def __init__(self, project_path: Path | str | Session) -> None:
        super().__init__()
        self.session = project_path if isinstance(project_path, Session) else open_session(project_path)
        self.job: Job | None = None
        self.viewer: RunningViewer | ViewerHandle | None = None  # the browser viewer, when open
        self.viewer_url: str | None = None
        self.last_job: dict[str, Any] = {}  # name -> (result or error text), for tests and the panel
        self.status: tuple[str, bool] = ("no run in progress", False)  # the status line when idle: text, error

    # -- screens ---------------------------------------------------------------------------------
    def on_mount(self) -> None:
        self.push_screen(SCREENS_BY_STEP[self.session.project.step]())
        self.set_interval(0.25, self._tick)
        self.set_interval(WATCH_S, self.watch_file)

    def goto(self, step: str) -> None:
        """Show the screen of ``step`` (any step, any time: revisiting is always allowed)."""
        self.switch_screen(SCREENS_BY_STEP[step]())

    def get_system_commands(self, screen: Screen) -> Iterable[SystemCommand]:
        for i, s in enumerate(STEPS):
            yield SystemCommand(
                f"Step {i + 1}: {s.title}", f"go to the {s.title.lower()} step", lambda step=s.id: self.goto(step)
            )
        yield from super().get_system_commands(screen)

    def save_project(self) -> bool:
        """Save the session's project, merged with what other programs saved meanwhile (``project.sync``).
        When the file cannot be written (disk full, read-only, invalid since another program saved it) say
        so on the status line, in the title and in a notification, keep every entry in memory (the next
        edit saves them all again) and return False. A conflict (the same key or point changed here and
        elsewhere) keeps the file's value and asks."""
        try:
            res = self.session.save()
        except (OSError, FieldToolError) as e:
            why = (e.strerror or str(e)) if isinstance(e, OSError) else str(e)
            self.status = (f"NOT SAVED: {why}; your entries are kept here and written at the next edit", True)
            self.notify(self.status[0], severity="error", timeout=10)
            ok = False
        else:
            if self.status[1] and self.status[0].startswith("NOT SAVED"):
                self.status = (f"saved {self.session.path.name}", False)
            ok = True
            if res is not None:
                self._after_merge(res)
        if isinstance(self.screen, StepScreen):
            self.show_status(self.screen)
            self.screen.update_title()
        return ok

    def watch_file(self) -> None:
        """Take in a change another program (the viewer, a text editor, ``calibrate --project``) made to the
        project file: the open step shows it at once."""
        err_before = self.session.sync.error
        screen = self.screen
        before = (
            {r.field.key: r.field.format(r.field.get(self.session.project)) for r in screen.rows}
            if isinstance(screen, StepScreen)
            else None
        )  # to tell typing not yet taken in from old text
        try:
            res = self.session.poll()
        except FieldToolError as e:  # this window's own values no longer fit the merged file
            self.notify(f"the project file changed elsewhere and cannot be merged: {e}", severity="error")
            return
        err = self.session.sync.error
        if err and err != err_before:
            self.status = (f"NOT SAVED: {err}", True)
            self.notify(
                f"the project file was changed by another program and is not valid now: {err}",
                severity="error",
                timeout=12,
            )
            if isinstance(self.screen, StepScreen):
                self.show_status(self.screen)
                self.screen.update_title()
        if res is None:
            return
        if (
            not err
            and self.status[1]
            and self.status[0].startswith("NOT SAVED")
            and "another program" in self.status[0]
        ):
            self.status = (f"{self.session.path.name} is valid again", False)
        self._after_merge(res, before)
        if res.theirs_changed:
            self.status = (
                f"changed in {self.session.path.name} by another program: "
                f"{', '.join(res.theirs_changed[:4])}{' …' if len(res.theirs_changed) > 4 else ''}",
                False,
            )
            if self.viewer is not None and getattr(self.viewer, "in_process", False):
                self.viewer_reload()
        if isinstance(self.screen, StepScreen):
            self.show_status(self.screen)

    def _after_merge(self, res: SaveResult, before: dict[str, str] | None = None) -> None:
        """Show what another program changed in the open step; ask about conflicts (a field being typed in
        whose key changed elsewhere is one)."""
        screen = self.screen
        conflicts = list(res.conflicts)
        if isinstance(screen, StepScreen):
            keys = res.theirs_changed + [c.key for c in res.conflicts]
            if keys:
                conflicts += screen.show_keys(keys, before)
            if res.theirs_changed:
                screen.update_title()
        if conflicts:
            self.ask_conflicts(conflicts)

    def ask_conflicts(self, conflicts: list[Conflict]) -> None:
        """The file's values are kept; both are shown and the operator may put this window's back."""
        self.last_conflicts = conflicts
        self.notify("; ".join(c.text() for c in conflicts[:3]), severity="warning", timeout=15)

        def chosen(use_mine: bool | None) -> None:
            if isinstance(self.screen, StepScreen):
                for row in self.screen.rows:
                    row.held = False
            if not use_mine:
                if isinstance(self.screen, StepScreen):  # rows still holding this window's text show the file's
                    self.screen.show_keys([c.key for c in conflicts])
                return
            data = put_mine_back(project_to_dict(self.session.project), conflicts)
            try:
                adopt(self.session.project, project_from_dict(data, self.session.project.root))
            except FieldToolError as e:  # this window's text did not make a value: the file's stays
                self.notify(f"yours cannot be used ({e}); the file's value stays", severity="error")
                if isinstance(self.screen, StepScreen):
                    self.screen.show_keys([c.key for c in conflicts])
                return
            self.save_project()
            if isinstance(self.screen, StepScreen):
                self.screen.show_keys([c.key for c in conflicts])

        if not isinstance(self.screen, ConflictScreen):
            self.push_screen(ConflictScreen(conflicts), chosen)

    # -- long work -------------------------------------------------------------------------------
    def job_running(self) -> bool:
        return self.job is not None

    def start_job(self, name: str, title: str, fn: Callable[[Job], Any]) -> bool:
        """Run ``fn(job)`` in a worker thread; one run at a time."""
        if self.job is not None:
            self.notify(f"{self.job.title} is still running; wait or press escape to cancel it", severity="warning")
            return False
        job = Job(name, title)
        self.job = job
        self.last_job.pop(name, None)
        self.run_worker(lambda: fn(job), name=name, group="jobs", thread=True, exit_on_error=False)
        self.refresh_bindings()
        self._tick()
        return True

    def _tick(self) -> None:
        if self.job is not None and isinstance(self.screen, StepScreen):
            line = self.screen.status_line()
            if line is not None:
                line.show_job(self.job)

    def show_status(self, screen: StepScreen) -> None:
        """Fill the status line of a screen: the running job, or how the last one ended."""
        line = screen.status_line()
        if line is None:
            return
        if self.job is not None:
            line.show_job(self.job)
        else:
            line.show_message(*self.status)

    def on_worker_state_changed(self, event: Worker.StateChanged) -> None:
        if event.worker.group != "jobs" or self.job is None:
            return
        state = event.state
        if state not in (WorkerState.SUCCESS, WorkerState.ERROR, WorkerState.CANCELLED):
            return
        job, self.job = self.job, None
        took = time.monotonic() - job.t0
        error = event.worker.error if state == WorkerState.ERROR else None
        if state == WorkerState.SUCCESS:
            result = event.worker.result
            self._store_result(job.name, result)
            self.last_job[job.name] = result
            text, is_error = self._done_text(job, result, took), False
        else:
            text, is_error = describe_error(job.title, error, took)
            self.last_job[job.name] = text
        self.refresh_bindings()
        self.status = (text, is_error)
        screen = self.screen
        if isinstance(screen, StepScreen):
            self.show_status(screen)
            screen.on_job_finished(job.name, self.last_job[job.name])
        if is_error:  # the status line already says it; a toast only for what must not be missed
            self.notify(text, severity="error", timeout=8)

    def _store_result(self, name: str, result: Any) -> None:
        s = self.session
        if name == "piv" and isinstance(result, dict) and "stats" in result:
            s.piv_preview = result
        elif name == "calibration":
            s.calibration_run = result
        elif name == "stabilize":
            s.ui["stabilization"] = result

    @staticmethod
    def _done_text(job: Job, result: Any, took: float) -> str:
        if isinstance(result, dict) and "discharge_m3s" in result:
            return f"{job.title} done in {took:.1f} s: discharge {result['discharge_m3s']:.4f} m³/s"
        return f"{job.title} done in {took:.1f} s"

    def action_cancel_job(self) -> None:
        if self.job is not None:
            self.job.cancel()
            self.job.stage = "cancelling"

    def check_action(self, action: str, parameters: tuple) -> bool | None:
        if action == "cancel_job":
            return self.job is not None
        return True

    async def action_quit(self) -> None:
        """Quit; a run in progress is cancelled (everything entered is already saved)."""
        if self.job is not None:
            self.job.cancel()
        if self.viewer is not None:
            self.viewer.stop()
            self.viewer = None
        self.exit()

    # -- viewer (clicks in a browser) ----------------------------------------------------------------
    def action_viewer(self) -> None:
        if self.viewer is not None:
            self.notify(f"viewer at {self.viewer_url} · over SSH: {ssh_line(self.viewer)}", timeout=10)
            return
        try:  # lazy: viser (0.15-0.3 s to import) only when the operator opens the viewer
            from fieldtool.viewer.server import start_viewer
        except ImportError as e:
            self.notify(f"the viewer is not available ({e}); type pixel points as 'x, y'", severity="warning")
            return
        running = running_viewer(self.session.path)  # one viewer per project: attach to the running one
        if running is not None:
            self.viewer = running
        else:
            try:
                self.viewer = start_viewer(
                    self.session.path, host="127.0.0.1", on_pick=self._pick_from_viewer
                )  # the project's port
            except Exception as e:  # noqa: BLE001 - no viewer must not stop the measurement
                self.notify(f"the viewer did not start: {e}; type pixel points as 'x, y'", severity="error")
                return
        self.viewer_url = self.viewer.url
        if running is not None:
            self.status = (
                f"attached to the viewer that runs already (pid {running.pid}); over SSH: {ssh_line(self.viewer)}",
                False,
            )
            if isinstance(self.screen, StepScreen):
                self.screen.update_title()
                self.show_status(self.screen)
            self.notify(
                f"viewer at {self.viewer_url} (already running, pid {running.pid}): its picks appear "
                "here within a second",
                timeout=12,
            )
            return
        if isinstance(self.screen, StepScreen):
            self.screen.update_title()
        self.status = (f"viewer over SSH: {ssh_line(self.viewer)}", False)  # the URL is in the title bar
        if isinstance(self.screen, StepScreen):
            self.show_status(self.screen)
        self.notify(
            f"viewer at {self.viewer_url}: focus a pixel field here, click in the browser; "
            f"over SSH first run on your computer: {ssh_line(self.viewer)}",
            timeout=12,
        )

    def show_in_viewer(self, kind: str) -> None:
        """Show an image (``viewer.images.KINDS``, e.g. "filtered") in the viewer, started if needed."""
        if self.viewer is None:
            self.action_viewer()
        if self.viewer is None:
            return
        try:
            self.viewer.show_image(kind)
        except Exception as e:  # noqa: BLE001 - the viewer is a help, never a stop
            self.notify(f"the viewer cannot show it: {e}", severity="warning")
            return
        self.notify(f"shown in the viewer at {self.viewer_url}", timeout=6)

    def _pick_from_viewer(self, key: str, value: Any) -> None:
        """Called from the viewer's thread after it saved a pick."""
        self.call_from_thread(self.viewer_picked, key, value)

    def viewer_picked(self, key: str, value: Any) -> None:
        """The viewer saved a pick (merged into the file by ``project.sync``): take the file's change in
        now, without waiting for the next look at the file, and without writing anything back."""
        self.watch_file()

    def viewer_focus(self, key: str) -> None:
        """Switch the viewer to the pick mode that fills ``key`` (a pixel field got the focus)."""
        if self.viewer is None:
            return

        base = key.split("[")[0]
        for name, spec in MODES.items():
            if spec.field == base:
                self.viewer.set_mode(name)
                return

    def viewer_reload(self) -> None:
        """Tell the viewer the project file changed (after a TUI edit)."""
        if self.viewer is not None:
            try:
                self.viewer.reload()
            except Exception as e:  # noqa: BLE001
                self.notify(f"viewer not updated: {e}", severity="warning")
