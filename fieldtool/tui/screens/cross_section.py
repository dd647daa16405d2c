"""Step 1: the cross-section, loaded from a file or created from a shape, with a plot of it."""

from __future__ import annotations

from textual.app import ComposeResult

from fieldtool.errors import FieldToolError
from fieldtool.processing import cross_section as xs
from fieldtool.project.model import atomic_write_bytes
from fieldtool.run.inputs import load_cross_section
from fieldtool.tui import keys
from fieldtool.tui.screens.base import StepScreen
from fieldtool.tui.widgets.plots import SectionPlot


def typed_level(project) -> float | None:
    w = project.water_level
    return w.value_m if w.method == "value" else None


class CrossSectionScreen(StepScreen):
    STEP = "cross_section"
    INTRO = "the surveyed bed, left to right bank"
    BINDINGS = keys.CROSS_SECTION

    def compose_extra(self) -> ComposeResult:
        yield SectionPlot(id="plot")

    def refresh_view(self) -> None:
        plot = self.query_one(SectionPlot)
        c = self.project.cross_section
        if not c.shape and not c.path.strip():  # nothing typed yet: say what to do, not that a file is missing
            plot.set_data(
                message="no cross-section yet: type the survey file's name above, or choose a shape as the source"
            )
            return
        try:
            cs = load_cross_section(self.project)
        except FieldToolError as e:
            plot.set_data(message=str(e))
            return
        level = typed_level(self.project)
        try:
            if level is not None:
                cs.check_level(level)
        except FieldToolError:
            level = None
        plot.set_data(cs.station, cs.elevation, level)

    def action_write_csv(self) -> None:
        """Write the created shape's points to a CSV beside the project (reusable with 'load a file')."""
        try:
            cs = load_cross_section(self.project)
        except FieldToolError as e:
            self.notify(str(e), severity="error")
            return
        name = f"cross_section_{self.project.cross_section.shape or 'copy'}.csv"
        atomic_write_bytes(self.project.root / name, xs.to_csv_text(cs).encode("utf-8"))
        self.notify(f"wrote {name} ({len(cs.station)} points) beside the project file")
