"""What the TUI tells the operator about reaching the picking viewer over SSH."""

from __future__ import annotations

from fieldtool.viewer.guard import ssh_hint


def ssh_line(viewer) -> str:
    """The port forward to run on the operator's computer to reach ``viewer`` (a running viewer
    handle): the viewer's own ``ssh_hint()`` where it has one, else the plain ``ssh -L`` line."""
    hint = getattr(viewer, "ssh_hint", None)
    if callable(hint):
        hint = hint()
    if isinstance(hint, str) and hint:
        return hint  # the same text as `fieldtool view` prints (viewer.guard.ssh_hint)
    return ssh_hint(viewer.port)
