"""Step 2: the clip (time range, every Nth frame) and whether to stabilise it."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import Static

from fieldtool.errors import FieldToolError
from fieldtool.tui import jobs, keys
from fieldtool.tui.screens.base import StepScreen, fieldtool_app


class VideoScreen(StepScreen):
    STEP = "video"
    INTRO = "the clip to analyse"
    BINDINGS = [keys.run("Test stabilisation")]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="clip-info")
        yield Static("", id="stab-info")

    def refresh_view(self) -> None:
        info = self.query_one("#clip-info", Static)
        try:
            src = self.session.inputs().source
        except FieldToolError as e:
            info.update(f"[red]{escape(str(e))}[/red]")
            return
        i = src.info
        n = src.estimated_count()
        kind = "image sequence" if i.is_sequence else "video"
        info.update(
            f"{kind}: {i.width} x {i.height} px · {i.fps:.2f} fps · {i.n_frames} frames · "
            f"{i.duration_s:.2f} s\nframes used: about {n} ({max(n - 1, 0)} pairs)"
        )
        st = self.query_one("#stab-info", Static)
        rep = self.session.ui.get("stabilization")
        if self.project.stabilize.enabled:
            text = (
                "ctrl+r registers the clip on its first frame and reports the residual motion. Order of the "
                "regions: any; type 'x0, y0, x1, y1' or pick two corners per region in the viewer (ctrl+o)."
            )
            if rep:
                text = (
                    f"stabilised {rep['frames']} frames: residual median {rep['median_px']:.2f} px, "
                    f"max {rep['max_px']:.2f} px; largest camera motion {rep['max_shift_px']:.1f} px"
                )
            st.update(text)
        else:
            st.update("")

    def check_action(self, action: str, parameters: tuple) -> bool | None:
        if action == "run":
            return self.project.stabilize.enabled
        return True

    def after_edit(self, field) -> None:
        if field.key.startswith("stabilize"):
            self.session.ui.pop("stabilization", None)
            self.refresh_bindings()

    def action_run(self) -> None:
        if self.errors():
            self.show_errors(self.errors())
            return
        p = jobs.snapshot(self.project)  # the project as it is now: the job runs on this copy
        fieldtool_app(self).start_job(
            "stabilize",
            "Stabilisation",
            lambda job: jobs.run_stabilization(p, job),
        )
