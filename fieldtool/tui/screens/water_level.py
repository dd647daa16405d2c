"""Step 5: water level: typed, from a wetted width, adapted Hellebaut, angle and height, image."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import Static

from fieldtool.errors import FieldToolError
from fieldtool.run.geometry import level_and_mapping
from fieldtool.run.inputs import load_cross_section
from fieldtool.tui import keys
from fieldtool.tui.screens.base import StepScreen
from fieldtool.tui.widgets.plots import SectionPlot


class WaterLevelScreen(StepScreen):
    STEP = "water_level"
    INTRO = "surface elevation in the section datum"
    BINDINGS = [keys.run("Compute level")]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="level-info")
        yield SectionPlot(id="plot")

    def compute(self):
        inputs = self.session.inputs()
        level, _ = level_and_mapping(self.project, inputs)
        return level, inputs.cross_section

    def refresh_view(self, computed: bool = False) -> None:
        plot = self.query_one(SectionPlot)
        info = self.query_one("#level-info", Static)
        cheap = self.project.water_level.method in ("value", "width")
        if computed or cheap:
            try:
                level, cs = self.compute()
            except FieldToolError as e:
                info.update(f"[red]{escape(str(e))}[/red]")
                try:
                    cs = load_cross_section(self.project)
                    plot.set_data(cs.station, cs.elevation, None)
                except FieldToolError as e2:
                    plot.set_data(message=str(e2))
                return
            unc = f" ± {level.uncertainty_m:.3f}" if level.uncertainty_m else ""
            info.update(
                f"water level {level.level_m:.3f}{unc} m · wetted width {cs.wetted_width(level.level_m):.2f} m"
                f" · wetted area {cs.wetted_area(level.level_m):.3f} m²"
            )
            plot.set_data(cs.station, cs.elevation, level.level_m)
            return
        info.update("ctrl+r computes the level with this method")
        try:
            cs = load_cross_section(self.project)
            plot.set_data(cs.station, cs.elevation, None)
        except FieldToolError as e:
            plot.set_data(message=str(e))

    def action_run(self) -> None:
        self.refresh_view(computed=True)
