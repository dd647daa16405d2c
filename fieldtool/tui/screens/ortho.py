"""Step 4: orthorectification from ground control points (GCPs), or skip it."""

from __future__ import annotations

from rich.text import Text
from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import Static

from fieldtool.errors import FieldToolError
from fieldtool.run.geometry import build_mapping
from fieldtool.tui import keys
from fieldtool.tui.screens.base import StepScreen

SCHEMATIC = (
    "P1 ──L1── P2   bank 1\n"
    "│ ╲      ╱ │   L5 = |P1P3|, L6 = |P2P4|\n"
    "L4  L5  L6 L2  water\n"
    "│ ╱      ╲ │   P1..P4 go round the quad\n"
    "P4 ──L3── P3   bank 2"
)


class OrthoScreen(StepScreen):
    STEP = "ortho"
    INTRO = "pixels -> metres on the water"
    BINDINGS = [keys.run("Check GCPs")]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="ortho-info")
        yield Static(Text(SCHEMATIC), id="schematic")

    def refresh_view(self) -> None:
        self.query_one("#schematic", Static).display = self.project.ortho.method == "distances"
        info = self.query_one("#ortho-info", Static)
        m = self.project.ortho.method
        if m == "none":
            info.update(
                "no GCPs: the image scale comes from the section's water edges and the wetted width at the "
                "water level; only for a camera looking straight down"
            )
        elif m == "pose":
            info.update("camera pose: needs the lens (step 3) and the water level (step 5); checked at step 5")
        else:
            info.update("ctrl+r solves the GCP geometry and reports its residual")

    def mapping(self):
        return build_mapping(self.project, self.session.inputs(), None)

    def action_run(self) -> None:
        info = self.query_one("#ortho-info", Static)
        if self.project.ortho.method not in ("distances", "world", "two_points"):
            self.refresh_view()
            return
        try:
            mp = self.mapping()
        except FieldToolError as e:
            info.update(f"[red]{escape(str(e))}[/red]")
            return
        if mp.method == "two_points":
            info.update(
                f"scale {mp.details['m_per_px'] * 1000:.2f} mm/px, rotation {mp.details['rotation_deg']:.1f}°; "
                "two points: exact, a straight-down view is assumed, not checked"
            )
            return
        res = f"{mp.residual_m * 1000:.1f} mm" if mp.residual_m is not None else "n/a"
        info.update(f"GCP geometry solved: residual of the distances {res}")
