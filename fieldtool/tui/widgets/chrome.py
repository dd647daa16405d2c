"""The frame around every step: title bar, step list, help line and the status line."""

from __future__ import annotations

import time

from rich.text import Text
from textual.widgets import OptionList, Static
from textual.widgets.option_list import Option

from fieldtool.tui.steps import STEPS

# sidebar mark per step state: ✓ validates, · something to enter, ! changed since the last result, ✗ invalid
MARKS = {"ok": ("✓", "green"), "todo": ("·", "yellow"), "stale": ("!", "red"), "invalid": ("✗", "bold red")}
SIDEBAR_TEXT = 21  # characters of a reason shown under a ✗ step (the sidebar is 24 wide)


class TitleBar(Static):
    """Project name, file, save state and the viewer address. The viewer's URL (with its key) is always shown
    whole while the viewer runs: the name and the file give way to it on a narrow (80 columns) terminal."""

    def show(self, name: str, file: str, note: str = "", url: str | None = None) -> None:
        width = self.size.width or (self.app.size.width if self.is_attached else 80) or 80
        tail = (f"· {note}" + (" " if url else "") if note else "") + (f"· viewer {url}" if url else "")
        room = width - len(" fieldtool ") - len(tail) - 1
        head = f" {name} · {file} "
        if len(head) > room:
            head = f" {name} "
        if len(head) > room:
            head = f" {name[: max(room - 3, 1)]}… " if room > 4 else " "
        t = Text()
        t.append(" fieldtool ", style="bold reverse")
        if " · " in head:
            n, f = head.split(" · ", 1)
            t.append(f"{n} ", style="bold")
            t.append(f"· {f}", style="dim")
        else:
            t.append(head, style="bold")
        if note:
            t.append(f"· {note}" + (" " if url else ""), style="italic")
        if url:
            t.append(f"· viewer {url}", style="bold")
        self.update(t)


class StepList(OptionList):
    """The steps in the thesis' order with their state: ✓ validates, · to enter, ! stale, ✗ invalid
    (with the reason on a second, dim line, in full in the help line when highlighted).

    Enter on a step jumps to it (the command palette, ctrl+p, does the same by name)."""

    def __init__(self, current: str, marks: dict[str, str], reasons: dict[str, str] | None = None) -> None:
        super().__init__(*self._make_options(current, marks, reasons or {}), id="steps")
        self.current = current
        self.reasons = dict(reasons or {})
        self.highlighted = [s.id for s in STEPS].index(current)

    @staticmethod
    def _make_options(current: str, marks: dict[str, str], reasons: dict[str, str]) -> list[Option]:
        out = []
        for i, s in enumerate(STEPS):
            mark = marks.get(s.id, "todo")
            sym, colour = MARKS[mark]
            t = Text(no_wrap=True, overflow="ellipsis")
            t.append(sym, style=f"bold {colour}")
            t.append(f"{i + 1:>2} {s.title}", style="bold reverse" if s.id == current else "")
            if mark == "invalid" and reasons.get(s.id):
                r = reasons[s.id]
                t.append("\n   " + (r if len(r) <= SIDEBAR_TEXT - 2 else r[: SIDEBAR_TEXT - 3] + "…"), style="red")
            out.append(Option(t, id=s.id))
        return out

    def set_marks(self, marks: dict[str, str], reasons: dict[str, str] | None = None) -> None:
        h = self.highlighted
        self.reasons = dict(reasons or {})
        self.clear_options()
        self.add_options(self._make_options(self.current, marks, self.reasons))
        self.highlighted = h


class HelpLine(Static):
    """Help of the focused parameter (key, unit, meaning, default), wrapped over as many lines as it
    needs; with the field's full message first when its entry is wrong."""


def clock(seconds: float | None) -> str:
    """m:ss (h:mm:ss from an hour), "--:--" when unknown."""
    if seconds is None:
        return "--:--"
    s = int(round(seconds))
    return f"{s // 60:d}:{s % 60:02d}" if s < 3600 else f"{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}"


def bar(done: int, total: int, width: int = 12) -> str:
    """A text progress bar: ``━`` done, ``─`` to do (``╸`` half a cell)."""
    if not total:
        return "─" * width
    f = max(0.0, min(1.0, done / total)) * width
    full = int(f)
    half = "╸" if f - full >= 0.5 and full < width else ""
    return "━" * full + half + "─" * (width - full - len(half))


def job_line(job, width: int = 78, now: float | None = None) -> str:
    """The status text of a running job in ``width`` characters: name and stage (shortened first),
    progress bar and count, elapsed and remaining time, and the cancel key (always kept)."""
    done, total = job.done, job.total
    elapsed = (time.monotonic() if now is None else now) - job.t0
    remaining = elapsed * (total - done) / done if total and done else None
    count = f" {done}/{total}" if total else ""
    head = f"▶ {job.title}: {job.stage or 'starting'}"
    tail = f" {bar(done, total, 8)}{count} · {clock(elapsed)} elapsed · {clock(remaining)} left · esc cancels"
    room = width - len(tail)
    if len(head) > room:
        head = head[: max(room - 1, 1)] + "…"
    return head + tail


class StatusLine(Static):
    """One line above the footer on every screen: the running job, or how the last one ended."""

    def show_job(self, job) -> None:
        self.set_class(False, "error")
        self.set_class(True, "running")
        self.update(Text(job_line(job, self.content_size.width or 78), no_wrap=True, overflow="ellipsis"))

    def show_message(self, text: str, error: bool = False) -> None:
        self.set_class(False, "running")
        self.set_class(error, "error")
        self.update(Text(text, no_wrap=True, overflow="ellipsis"))
