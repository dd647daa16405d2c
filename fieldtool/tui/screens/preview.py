"""The filter preview at the size of the terminal: first frame and filtered frame side by side.

The filtered frame is also written to ``out/filter_preview.png`` (the whole working frame, not only
the ROI), so the picking viewer can show it at full resolution (ctrl+o)."""

from __future__ import annotations

import numpy as np
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Footer, Static

from fieldtool.tui.screens.base import fieldtool_app
from fieldtool.tui.widgets.plots import GrayImage

PNG = "filter_preview.png"


class PreviewScreen(ModalScreen):
    """Before / after of the filter stack, as large as the terminal allows."""

    BINDINGS = [Binding("escape", "close", "Close"), Binding("ctrl+o", "viewer", "Open in the viewer")]

    def __init__(self, before: np.ndarray, after: np.ndarray, captions: tuple[str, str], png: str) -> None:
        super().__init__()
        self.before, self.after, self.captions, self.png = before, after, captions, png

    def compose(self) -> ComposeResult:
        with Vertical(id="preview-box"):
            yield Static(f"filter preview · esc closes · ctrl+o shows {self.png} in the viewer", id="preview-title")
            with Horizontal(id="preview-big"):
                yield GrayImage(id="big-before")
                yield GrayImage(id="big-after")
        yield Footer()

    def on_mount(self) -> None:
        self.query_one("#big-before", GrayImage).set_image(self.before, self.captions[0])
        self.query_one("#big-after", GrayImage).set_image(self.after, self.captions[1])

    def action_close(self) -> None:
        self.app.pop_screen()

    def action_viewer(self) -> None:
        fieldtool_app(self).show_in_viewer("filtered")
