"""Every key binding of the TUI, declared in one place.

Only control keys, function keys and escape are bound, never a bare printable key: an input may
have the focus on any screen, and typing there must never trigger an action. Keys that the Input
widget uses (ctrl+a/e/d/w/u/k/x/c/v) and keys terminals send for others (ctrl+h/i/j/m) are
avoided. Tab / shift+tab move between fields; enter opens a choice list.
"""

from __future__ import annotations

from textual.binding import Binding, BindingType

APP: list[BindingType] = [
    Binding("ctrl+q", "quit", "Quit", priority=True),
    Binding("escape", "cancel_job", "Cancel"),
    Binding("ctrl+o", "viewer", "Viewer"),
]

STEP: list[BindingType] = [
    Binding("ctrl+b", "back", "Back"),
    Binding("ctrl+n", "next", "Next"),
]


def run(label: str) -> Binding:
    """The step's main action (run / compute / preview), on ctrl+r."""
    return Binding("ctrl+r", "run", label)


FILTERS: list[BindingType] = [
    Binding("ctrl+t", "add_filter", "Add"),
    Binding("ctrl+y", "remove_filter", "Remove"),
]

CROSS_SECTION: list[BindingType] = [
    Binding("ctrl+s", "write_csv", "Save as CSV"),
]

RESULTS: list[BindingType] = [
    Binding("ctrl+g", "report", "Report"),
    Binding("ctrl+l", "overlay", "Overlay video"),  # run again with overlay.mp4 (the PIV field is reused)
]
