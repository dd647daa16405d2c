"""The frame around every step: title bar, step list, help line, and the run panel."""

from __future__ import annotations

import time

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import OptionList, ProgressBar, Static
from textual.widgets.option_list import Option

from ..steps import STEPS

MARKS = {"ok": ("✓", "green"), "todo": ("·", "yellow"), "stale": ("!", "red")}


class TitleBar(Static):
    """Project name, file, save state and the viewer address."""

    def show(self, name: str, file: str, note: str = "") -> None:
        t = Text()
        t.append(" fieldtool ", style="bold reverse")
        t.append(f" {name} ", style="bold")
        t.append(f"· {file} ", style="dim")
        if note:
            t.append(f"· {note}", style="italic")
        self.update(t)


class StepList(OptionList):
    """The steps in the thesis' order with their state: ✓ done, · to do, ! stale.

    Enter on a step jumps to it (the command palette, ctrl+p, does the same by name)."""

    def __init__(self, current: str, marks: dict[str, str]) -> None:
        super().__init__(*self._make_options(current, marks), id="steps")
        self.current = current
        self.highlighted = [s.id for s in STEPS].index(current)

    @staticmethod
    def _make_options(current: str, marks: dict[str, str]) -> list[Option]:
        out = []
        for i, s in enumerate(STEPS):
            sym, colour = MARKS[marks.get(s.id, "todo")]
            t = Text()
            t.append(sym, style=f"bold {colour}")
            t.append(f"{i + 1:>2} {s.title}", style="bold reverse" if s.id == current else "")
            out.append(Option(t, id=s.id))
        return out

    def set_marks(self, marks: dict[str, str]) -> None:
        h = self.highlighted
        self.clear_options()
        self.add_options(self._make_options(self.current, marks))
        self.highlighted = h


class HelpLine(Static):
    """Help of the focused parameter (key, unit, meaning, default)."""


def _clock(seconds: float | None) -> str:
    if seconds is None:
        return "--:--"
    s = int(round(seconds))
    return f"{s // 60:d}:{s % 60:02d}" if s < 3600 else f"{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}"


class JobPanel(Vertical):
    """Progress of a long run: stage, bar, elapsed and remaining time; escape cancels."""

    def compose(self) -> ComposeResult:
        yield Static("", id="job-label")
        yield ProgressBar(total=None, show_eta=False, id="job-bar")

    def on_mount(self) -> None:
        self.display = False

    def show_job(self, job) -> None:
        self.display = True
        bar = self.query_one(ProgressBar)
        bar.display = True
        self.query_one("#job-label", Static).set_class(False, "error")
        done, total = job.done, job.total
        elapsed = time.monotonic() - job.t0
        remaining = None
        if total and done:
            remaining = elapsed * (total - done) / done
        if total:
            bar.update(total=total, progress=done)
        label = f"{job.title}: {job.stage or 'starting'} {done}/{total or '?'}" \
                f" · elapsed {_clock(elapsed)} · remaining {_clock(remaining)} · esc cancels"
        self.query_one("#job-label", Static).update(Text(label))

    def show_message(self, text: str, error: bool = False) -> None:
        self.display = True
        self.query_one(ProgressBar).display = False
        lab = self.query_one("#job-label", Static)
        lab.update(Text(text))
        lab.set_class(error, "error")
