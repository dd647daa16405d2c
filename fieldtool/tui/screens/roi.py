"""Step 6: region of interest and masks (both optional)."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import Static

from fieldtool.errors import FieldToolError
from fieldtool.run.geometry import roi_and_mask
from fieldtool.tui.screens.base import StepScreen


class RoiScreen(StepScreen):
    STEP = "roi"
    INTRO = "where PIV runs, and what it ignores"

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="roi-info")

    def refresh_view(self) -> None:
        info = self.query_one("#roi-info", Static)
        try:
            roi, mask = self.check()
        except FieldToolError as e:
            info.update(f"[red]{escape(str(e))}[/red]")
            return
        h, w = self.session.inputs().shape
        area = f"x {roi[0]}..{roi[2]}, y {roi[1]}..{roi[3]} px" if roi else "the whole frame"
        masked = f" · {100.0 * mask.mean():.1f} % of the frame masked" if mask is not None else ""
        info.update(
            f"frame {w} x {h} px · PIV runs on {area}{masked}\n"
            "pick the ROI as two corners (top-left, bottom-right) and each mask as 3+ corners in the viewer"
        )

    def check(self):
        return roi_and_mask(self.project, self.session.inputs())
