"""What every step screen shares: the frame, the parameter rows, saving, next/back and errors."""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Horizontal, VerticalScroll
from textual.screen import Screen
from textual.widgets import Footer, OptionList, Static

from fieldtool.errors import FieldToolError
from fieldtool.project.sync import Conflict
from fieldtool.tui import keys
from fieldtool.tui.checks import core_check, is_missing
from fieldtool.tui.fields import Field
from fieldtool.tui.steps import STEP_BY_ID, STEP_IDS, fields_for
from fieldtool.tui.widgets.chrome import HelpLine, StatusLine, StepList, TitleBar
from fieldtool.tui.widgets.field_row import FieldRow, field_id

if TYPE_CHECKING:  # the app imports the screens
    from fieldtool.tui.app import FieldToolApp

GENERAL_HELP = "tab / shift+tab: next / previous field · enter: open a list · ctrl+p: jump to a step"


def fieldtool_app(screen: Screen) -> FieldToolApp:
    """The app ``screen`` runs in, typed as fieldtool's (textual's ``Screen.app`` is a plain ``App``)."""
    return cast("FieldToolApp", screen.app)


class StepScreen(Screen):
    """A step of the measurement: its parameters, an optional action (ctrl+r) and next/back."""

    STEP = ""
    INTRO = ""  # one line: what this step is for
    BINDINGS = keys.STEP
    AUTO_FOCUS = None

    def __init__(self) -> None:
        super().__init__(name=self.STEP)
        self.rows: list[FieldRow] = []

    # -- helpers ---------------------------------------------------------------------------------
    @property
    def session(self):
        return self.app.session

    @property
    def project(self):
        return self.session.project

    def fields(self) -> list[Field]:
        return fields_for(self.STEP, self.session.ui)

    # -- layout ------------------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield TitleBar(id="titlebar")
        with Horizontal(id="body"):
            marks = self.session.step_marks()
            yield StepList(self.STEP, marks, self.session.mark_reasons)
            with VerticalScroll(id="main"):
                n = STEP_IDS.index(self.STEP) + 1
                heading = Text.from_markup(f"[b]{n}. {STEP_BY_ID[self.STEP].title}[/b]  [dim]{self.INTRO}[/dim]")
                heading.no_wrap, heading.overflow = True, "ellipsis"
                yield Static(heading, id="heading")
                yield Static("", id="step-errors")
                yield from self.compose_top()
                seen: set[str] = set()
                for f in self.fields():
                    fid = field_id(f)
                    if fid in seen:
                        fid += "-2"
                    seen.add(fid)
                    row = FieldRow(f, id=fid)
                    self.rows.append(row)
                    yield row
                yield from self.compose_extra()
        yield HelpLine(GENERAL_HELP, id="help")
        yield StatusLine(id="status")
        yield Footer()

    def compose_top(self) -> ComposeResult:
        """Widgets above the parameter rows."""
        yield from ()

    def compose_extra(self) -> ComposeResult:
        """Widgets below the parameter rows (plots, tables, results)."""
        yield from ()

    def on_mount(self) -> None:
        if self.project.step != self.STEP:
            self.project.step = self.STEP
            fieldtool_app(self).save_project()
        self.query_one("#step-errors", Static).display = False
        fieldtool_app(self).show_status(self)
        self.update_title()
        self.update_visibility()
        self.refresh_view()
        self.focus_first()

    def focus_first(self) -> None:
        """Focus the first field still to be entered, else the first field (saves tabs on arrival)."""
        for row in self.rows:
            err = row.current_error() if row.display else None
            if err and is_missing(err):
                row.control.focus()
                return
        for w in self.query("#main Input, #main Select, #main OptionList, #main DataTable"):
            if (
                w.display
                and w.parent is not None
                and all(a.display for a in w.ancestors_with_self if hasattr(a, "display"))
            ):
                w.focus()
                return

    def update_title(self, note: str = "") -> None:
        status = getattr(self.app, "status", ("", False))
        if not note and status[1] and status[0].startswith("NOT SAVED"):
            note = "NOT SAVED"
        viewer = getattr(self.app, "viewer_url", None)  # shown whole, beside the save state, while the viewer runs
        self.query_one(TitleBar).show(self.project.name, self.session.path.name, note or "saved", url=viewer)

    def update_visibility(self) -> None:
        for row in self.rows:
            row.display = row.field.visible(self.project)

    def refresh_view(self) -> None:
        """Redraw what depends on the project (plots, info lines). Called after every edit."""

    def refresh_marks(self) -> None:
        marks = self.session.step_marks()
        self.query_one(StepList).set_marks(marks, self.session.mark_reasons)

    # -- events ------------------------------------------------------------------------------------
    def on_field_row_edited(self, event: FieldRow.Edited) -> None:
        fieldtool_app(self).save_project()
        fieldtool_app(self).viewer_reload()
        self.after_edit(event.row.field)
        self.update_visibility()
        for row in self.rows:
            if row is not event.row:
                row.refresh_error()
        self.refresh_view()
        self.refresh_marks()
        self.update_title()
        self.query_one("#step-errors", Static).display = False
        if self.app.focused is not None and event.row in self.app.focused.ancestors:
            self.show_row_help(event.row)

    def after_edit(self, field: Field) -> None:
        """Hook after a parameter changed (already saved)."""

    def on_descendant_focus(self, event) -> None:
        help_line = self.query_one(HelpLine)
        node = event.widget
        while node is not None and not isinstance(node, FieldRow):
            node = node.parent
        if isinstance(node, FieldRow):
            self.show_row_help(node)
            if node.field.pickable:
                fieldtool_app(self).viewer_focus(node.field.key)
        else:
            help_line.update(Text(self.focus_help(event.widget)))

    def show_row_help(self, row: FieldRow) -> None:
        """The help line of a field: its full message first when its entry is wrong, then its help."""
        t = Text()
        if row.error and is_missing(row.error):
            t.append("✗ required · ", style="bold red")
        elif row.error:
            t.append(f"✗ {row.error}\n", style="bold red")
        t.append(row.field.help_line(self.project))
        self.query_one(HelpLine).update(t)

    def focus_help(self, widget) -> str:
        if isinstance(widget, StepList):
            return self.step_help(widget)
        return GENERAL_HELP

    def step_help(self, steps: StepList) -> str:
        i = steps.highlighted
        sid = STEP_IDS[i] if i is not None else self.STEP
        reason = steps.reasons.get(sid)
        head = f"{STEP_BY_ID[sid].title}: {reason}\n" if reason else ""
        return head + "up / down, enter: go to that step (✓ validates, · to enter, ✗ wrong, ! changed since the result)"

    def on_option_list_option_highlighted(self, event: OptionList.OptionHighlighted) -> None:
        if isinstance(event.option_list, StepList) and self.app.focused is event.option_list:
            self.query_one(HelpLine).update(Text(self.step_help(event.option_list)))

    def on_option_list_option_selected(self, event: OptionList.OptionSelected) -> None:
        if event.option_list.id == "steps":
            event.stop()
            assert event.option.id is not None  # each option of the step list has its step's id
            fieldtool_app(self).goto(event.option.id)

    # -- checks ----------------------------------------------------------------------------------
    def errors(self) -> list[str]:
        """Everything that blocks "next": the rows' messages, then the step's own check."""
        msgs = [m for m in (row.current_error() for row in self.rows if row.display) if m]
        if msgs:
            return msgs
        msgs = self.session.step_problems(self.STEP, core=False)
        if msgs:
            return msgs
        try:
            self.step_check()
        except FieldToolError as e:
            return [str(e)]
        return []

    def step_check(self) -> None:
        """Check the step with the core functions; raise FieldToolError with the user's message."""
        core_check(self.session, self.STEP)

    def show_errors(self, msgs: list[str]) -> None:
        """What blocks "next": one message whole, several one line each (a missing entry as "key:
        required"); the field at fault gets the focus, so the help line shows its full message."""
        box = self.query_one("#step-errors", Static)
        lines = [m.split(" — ")[0] if is_missing(m) else m for m in msgs]
        one_line = len(lines) > 1
        box.update(
            Text("\n".join(f"✗ {m}" for m in lines), no_wrap=one_line, overflow="ellipsis" if one_line else None)
        )
        box.display = bool(msgs)
        if msgs:
            for row in self.rows:
                if row.display and row.current_error():
                    row.control.focus()
                    break
            self.query_one("#main", VerticalScroll).scroll_home(animate=False)

    # -- actions ---------------------------------------------------------------------------------
    def action_next(self) -> None:
        msgs = self.errors()
        if msgs:
            self.show_errors(msgs)
            self.app.bell()
            return
        i = STEP_IDS.index(self.STEP)
        if i + 1 < len(STEP_IDS):
            fieldtool_app(self).goto(STEP_IDS[i + 1])

    def action_back(self) -> None:
        i = STEP_IDS.index(self.STEP)
        if i > 0:
            fieldtool_app(self).goto(STEP_IDS[i - 1])

    # -- runs (the app owns the worker; the screen shows it) ----------------------------------------
    def status_line(self) -> StatusLine | None:
        """The screen's status line (None while the screen is being built or torn down)."""
        return next(iter(self.query(StatusLine)), None)

    def on_job_finished(self, name: str, result) -> None:
        """A run of this session finished while this screen is shown (result already stored)."""
        self.refresh_view()
        self.refresh_marks()

    # -- viewer picks and other programs' edits ---------------------------------------------------
    def show_keys(self, keys: list[str], before: dict[str, str] | None = None) -> list:
        """Show the project's values of the changed ``keys`` (``project.sync`` keys: dotted, ``[i]`` per
        point) in the rows that display them, and only in those: a row being typed in whose own key did not
        change keeps its text (a refresh must never put an old value back into it).

        ``before``: each row's text as the project's value gave it before the change came in. A row whose
        text differs from it holds typing not yet taken in: it is left as it is and returned as a Conflict
        (its text, the file's value) for the app to ask about."""

        def hit(row_key: str) -> bool:
            return any(row_key == k or k.startswith(row_key + "[") or row_key.startswith(k + "[") for k in keys)

        shown = False
        pending = []
        for row in self.rows:
            if hit(row.field.key):
                mid_typing = (
                    before is not None
                    and row.display
                    and row.field.key in keys
                    and row.field.key in before
                    and row.text() != before[row.field.key]
                )
                if mid_typing:  # this very key changed elsewhere while its row holds typing not taken in
                    try:
                        typed = row.field.parse(row.text())
                    except ValueError:
                        typed = row.text()
                    pending.append(Conflict(row.field.key, typed, row.field.get(self.project)))
                    row.held = True  # its typing is kept on screen, not stored, until the operator chose
                    continue
                text = row.field.format(row.field.get(self.project))
                if row.text() != text:
                    row.set_text(text)
                row.refresh_error()
                shown = True
        if shown:
            self.update_visibility()
            self.refresh_view()
            self.refresh_marks()
        return pending

    def show_value(self, key: str) -> bool:
        """Show the project's value of ``key`` (set elsewhere, e.g. by a viewer pick) in its rows."""
        shown = False
        for row in self.rows:
            if row.field.key == key or row.field.key.startswith(key + "["):
                row.set_text(row.field.format(row.field.get(self.project)))
                row.refresh_error()
                shown = True
        if shown:
            self.update_visibility()
            self.refresh_view()
            self.refresh_marks()
        return shown
