"""Step 9: section of interest (two water edges), number of subsections and velocity index."""

from __future__ import annotations

import numpy as np
from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import Static

from fieldtool.errors import FieldToolError
from fieldtool.processing.discharge import default_alpha
from fieldtool.tui import keys
from fieldtool.tui.checks import section_geometry
from fieldtool.tui.screens.base import StepScreen


class SectionScreen(StepScreen):
    STEP = "section"
    INTRO = "where the discharge is computed"
    BINDINGS = [keys.run("Check section")]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="section-info")

    def geometry(self):
        return section_geometry(self.session)

    def refresh_view(self, checked: bool = False) -> None:
        info = self.query_one("#section-info", Static)
        if not checked:
            info.update("P1 is the LEFT water edge looking downstream; ctrl+r checks the section on the cross-section")
            return
        try:
            geom, level, cs = self.geometry()
        except FieldToolError as e:
            info.update(f"[red]{escape(str(e))}[/red]")
            return

        edges = geom.station_edges
        depth = cs.wetted_area(level.level_m, edges[0], edges[-1]) / max(edges[-1] - edges[0], 1e-9)
        alpha = self.project.section.alpha
        a = (
            f"{alpha:g} (typed)"
            if alpha is not None
            else f"{default_alpha(depth):g} (default for mean depth {depth:.2f} m)"
        )
        info.update(
            f"section {geom.length_m:.2f} m long, stations {edges[0]:.2f} .. {edges[-1]:.2f} m, "
            f"{len(edges) - 1} subsections of {np.diff(edges).mean():.2f} m · velocity index {a}"
        )

    def action_run(self) -> None:
        self.refresh_view(checked=True)
