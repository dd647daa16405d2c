"""One exception family for everything a person in the field can fix.

Every message names the file or field at fault and says what to do about it. The CLI prints the
message without a traceback and exits with code 2; the TUI shows it and stays on its step.
"""


class FieldToolError(Exception):
    """An input problem the user can fix. ``str(err)`` is the whole message."""


class InputFileError(FieldToolError):
    """A file is missing, unreadable or of the wrong format."""


class ParameterError(FieldToolError):
    """A parameter is out of range, of the wrong type, or inconsistent with another one."""


class GeometryError(FieldToolError):
    """Picked points, distances or levels do not make a valid geometry."""


class Cancelled(FieldToolError):
    """The user cancelled a long computation."""


class FieldToolWarning(UserWarning):
    """Something the user should know that does not stop the work (the CLI prints it as one line)."""
