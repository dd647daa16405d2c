"""The question asked when this TUI and another editor (the viewer, a text editor) changed the same key or
point to different values: the file's value was kept (see ``project.sync``); both are shown here and the
operator keeps it (escape, ``k``) or puts this window's value back (``m``)."""

from __future__ import annotations

from typing import ClassVar

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Static

from fieldtool.project.sync import Conflict


class ConflictScreen(ModalScreen[bool]):
    """Dismissed with True to use this window's values, False to keep the file's (the default)."""

    DEFAULT_CSS = """
    ConflictScreen { align: center middle; }
    ConflictScreen > Vertical { width: 76; height: auto; max-height: 20; border: thick $warning; padding: 0 1;
                                background: $surface; }
    ConflictScreen Button { margin: 1 1 0 0; }
    """
    BINDINGS: ClassVar = [Binding("escape,k", "keep", "keep the file's"), Binding("m", "mine", "use mine")]

    def __init__(self, conflicts: list[Conflict]) -> None:
        super().__init__()
        self.conflicts = conflicts

    def compose(self) -> ComposeResult:
        t = Text("Changed here and by another program at once\n", style="bold")
        for c in self.conflicts[:8]:
            t.append(f"• {c.text()}\n")
        if len(self.conflicts) > 8:
            t.append(f"… and {len(self.conflicts) - 8} more\n")
        t.append(
            "The file's value is kept (it is what the other window shows). m: put yours back; k / escape: "
            "keep the file's."
        )
        with Vertical():
            yield Static(t, id="conflict-text")
            yield Button("Keep the file's (k)", id="keep", variant="primary")
            yield Button("Use mine (m)", id="mine")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "mine")

    def action_keep(self) -> None:
        self.dismiss(False)

    def action_mine(self) -> None:
        self.dismiss(True)
