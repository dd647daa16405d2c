"""Step 3: lens calibration: skip, load a file, or calibrate from a checkerboard video."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.containers import Horizontal
from textual.markup import escape
from textual.widgets import Label, Select, Static

from fieldtool.errors import FieldToolError, ParameterError
from fieldtool.processing.calibration import load_calibration
from fieldtool.tui import jobs, keys
from fieldtool.tui.screens.base import StepScreen, fieldtool_app
from fieldtool.tui.steps import CALIBRATION_MODES


class CalibrationScreen(StepScreen):
    STEP = "calibration"
    INTRO = "lens distortion and field of view"
    BINDINGS = [keys.run("Calibrate")]

    def compose_top(self) -> ComposeResult:
        with Horizontal(classes="field-line", id="mode-line"):
            yield Label("Calibration", classes="field-label")
            yield Select(
                CALIBRATION_MODES,
                value=self.session.ui["calibration_mode"],
                allow_blank=False,
                compact=True,
                id="mode",
                type_to_search=False,
            )

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="lens-info")

    def on_select_changed(self, event: Select.Changed) -> None:
        if event.select.id != "mode":
            return
        event.stop()
        mode = event.value
        if mode == self.session.ui["calibration_mode"]:
            return
        self.session.ui["calibration_mode"] = mode
        c = self.project.calibration
        if mode == "skip":
            c.path, c.checkerboard_video = "", ""
        elif mode == "load":
            c.checkerboard_video = ""
        elif mode == "run" and not c.path:
            c.path = "calibration.toml"
        fieldtool_app(self).save_project()
        fieldtool_app(self).goto(self.STEP)  # rebuild the rows for the mode

    def focus_first(self) -> None:
        self.query_one("#mode", Select).focus()

    def refresh_view(self) -> None:
        info = self.query_one("#lens-info", Static)
        mode = self.session.ui["calibration_mode"]
        run = self.session.calibration_run
        if mode == "skip":
            info.update(
                "no lens correction: fine for most phone and action-camera clips of a small river; "
                "needed for the angle-and-height water level (field of view)"
            )
            return
        if mode == "run" and run is not None:
            fx, fy, fd = run["fov_deg"]
            state = (
                ""
                if self.session.calibration_state() == "current"
                else " [red]settings changed since: run it again (ctrl+r)[/red]"
            )
            info.update(
                f"calibrated from {run['views']} board views: RMS reprojection error {run['rms_px']:.3f} px; "
                f"FOV {fx:.1f} x {fy:.1f} deg (diagonal {fd:.1f}); saved as {self.project.calibration.path}" + state
            )
            return
        if mode == "run" and self.session.calibration_state() != "current":
            info.update("ctrl+r runs the calibration; it is written to the 'Save as' file and used from then on")
            return
        try:
            lens = self._load()
        except FieldToolError as e:
            info.update(f"[red]{escape(str(e))}[/red]")
            return
        fx, fy, fd = lens.fov_deg
        rms = f"RMS {lens.rms_px:.3f} px · " if lens.rms_px is not None else ""
        info.update(
            f"lens for {lens.image_size[0]} x {lens.image_size[1]} px: {rms}FOV {fx:.1f} x {fy:.1f} deg "
            f"(diagonal {fd:.1f})"
        )

    def _load(self):
        if not self.project.calibration.path:
            raise ParameterError("calibration.path: no calibration file given")
        return load_calibration(self.project.resolve(self.project.calibration.path))

    def step_check(self) -> None:
        mode = self.session.ui["calibration_mode"]
        if mode == "skip":
            return
        if mode == "run" and self.session.calibration_state() != "current":
            raise ParameterError("calibration: run the calibration (ctrl+r) first, or choose skip / load")
        self._load()

    def check_action(self, action: str, parameters: tuple) -> bool | None:
        if action == "run":
            return self.session.ui["calibration_mode"] == "run"
        return True

    def action_run(self) -> None:
        msgs = [r.current_error() for r in self.rows if r.display]
        errors = [m for m in msgs if m]
        if errors:
            self.show_errors(errors)
            return
        p = jobs.snapshot(self.project)  # the project as it is now: the job runs on this copy
        fieldtool_app(self).start_job(
            "calibration",
            "Calibration",
            lambda job: jobs.run_calibration(p, job),
        )
