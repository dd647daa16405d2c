"""One parameter: label with unit, an input (or a choice list), and its error message.

Typing is parsed and checked at once. A value that parses is written to the project (and the
project file saved by the screen) even when a cross-check fails, so nothing typed is lost; the
message stays under the field and "next" is refused until it is fixed.
"""

from __future__ import annotations

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.widgets import Input, Label, Select, Static

from fieldtool.tui.checks import is_missing
from fieldtool.tui.fields import Field
from fieldtool.tui.widgets.path_suggester import PathSuggester


def field_id(field: Field) -> str:
    """A widget id for a field key (``ortho.gcp_px[0]`` -> ``f-ortho-gcp_px-0``)."""
    return "f-" + field.key.replace(".", "-").replace("[", "-").replace("]", "")


PLACEHOLDER_MAX = 30  # characters an input shows at 80 x 24 (placeholders are kept within it)


class FieldRow(Vertical):
    """A labelled input bound to one project key."""

    class Edited(Message):
        """The project value of ``row.field`` changed."""

        def __init__(self, row: FieldRow) -> None:
            super().__init__()
            self.row = row

    def __init__(self, field: Field, *, id: str | None = None) -> None:
        super().__init__(id=id or field_id(field), classes="field-row")
        self.field = field
        self.error: str | None = None
        self._text_error: str | None = None
        self.held = False  # its key changed elsewhere while typed in: nothing is stored until the operator chose

    @property
    def project(self):
        return self.app.session.project

    def compose(self) -> ComposeResult:
        f = self.field
        unit = f" [{f.unit}]" if f.unit else ""
        with Horizontal(classes="field-line"):
            yield Label(Text(f"{f.label}{unit}"), classes="field-label")
            value = f.get(self.project)
            if f.kind == "choice":
                options = [(label, v) for label, v in f.choices]
                known = [v for _, v in options]
                yield Select(
                    options,
                    value=value if value in known else known[0],
                    allow_blank=False,
                    compact=True,
                    id="input",
                    type_to_search=False,
                )
            else:
                ph = f.placeholder(self.project) if callable(f.placeholder) else f.placeholder
                # select_on_focus: typing into a field that holds "0" replaces it (not "0abc")
                suggester = PathSuggester(self.project.root, f.key) if f.kind == "path" else None
                yield Input(
                    f.format(value), placeholder=ph, compact=True, id="input", select_on_focus=True, suggester=suggester
                )
        yield Static("", classes="field-error")

    def on_mount(self) -> None:
        self.refresh_error()

    @property
    def control(self) -> Input | Select:
        return self.query_one("#input")  # type: ignore[return-value]

    # -- typing --------------------------------------------------------------------------------
    def on_input_changed(self, event: Input.Changed) -> None:
        event.stop()
        f = self.field
        try:
            value = f.parse(event.value)
        except ValueError as e:
            # the text does not parse: the project keeps its last good value
            self._text_error = f"{f.key}: {e}" + (f" ({f.unit})" if f.unit else "")
            self._show(self._text_error)
            return
        self._text_error = None
        self._store(value)

    def on_select_changed(self, event: Select.Changed) -> None:
        event.stop()
        self._text_error = None
        self._store(event.value)

    def _store(self, value) -> None:
        f = self.field
        if self.held:
            return
        current = f.get(self.project)
        if current is not None and value is not None and f.format(current) == f.format(value):
            value = current  # the text shows the value rounded (pixels: 2 decimals): not an edit, keep every digit
        if current != value:
            try:
                f.set(self.project, value)
            except IndexError:
                pass  # an item beyond the end of its list: only the message is shown
            else:
                self.post_message(self.Edited(self))
        self.refresh_error()

    def set_text(self, text: str) -> None:
        """Show ``text``, the project's value of this row (set elsewhere: a viewer pick, another program's save),
        in the input. No Input.Changed is posted: that message is handled later, and storing the text then
        would put this value back over an edit made in between (a list row shown after the viewer's pick,
        stored after P2 was typed, took P2's old value back)."""
        ctl = self.control
        if isinstance(ctl, Input):
            with self.prevent(Input.Changed):
                ctl.value = text
            ctl.cursor_position = len(text)
            self._text_error = None

    def text(self) -> str:
        ctl = self.control
        return ctl.value if isinstance(ctl, Input) else ""

    # -- messages ------------------------------------------------------------------------------
    def current_error(self) -> str | None:
        """The message to show for this field now (text that does not parse, or a failed check)."""
        if not self.field.visible(self.project):
            return None
        if self._text_error:
            return self._text_error
        return self.field.validate(self.field.get(self.project), self.project)

    def refresh_error(self) -> None:
        self._show(self.current_error())

    def _show(self, msg: str | None) -> None:
        """A wrong entry: one line under the field, without the key (the label says it); the help
        line shows the full message when the field has the focus. A missing entry takes no line:
        the label turns red and the empty input says "required"."""
        self.error = msg
        missing = msg is not None and bool(msg) and is_missing(msg)
        box = self.query_one(".field-error", Static)
        box.update(
            Text(short_message(msg, self.field.key), no_wrap=True, overflow="ellipsis") if msg and not missing else ""
        )
        box.display = bool(msg) and not missing
        self.set_class(bool(msg), "-invalid")
        ctl = self.control
        if isinstance(ctl, Input):
            ph = self.field.placeholder(self.project) if callable(self.field.placeholder) else self.field.placeholder
            full = f"✗ required · {ph}" if ph else "✗ required"
            ctl.placeholder = (full if len(full) <= PLACEHOLDER_MAX else "✗ required") if missing else ph


def short_message(msg: str, key: str) -> str:
    """The one-line form of a field's message: "✗ " and the message without the leading key."""
    if msg.startswith(key + ": "):
        msg = msg[len(key) + 2 :]
    return "✗ " + msg
