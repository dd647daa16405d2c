"""What the TUI tells the operator about reaching the picking viewer over SSH."""

from __future__ import annotations


def ssh_line(viewer) -> str:
    """The port forward to run on the operator's computer to reach ``viewer`` (a running viewer
    handle): the viewer's own ``ssh_hint()`` where it has one, else the plain ``ssh -L`` line."""
    hint = getattr(viewer, "ssh_hint", None)
    if callable(hint):
        return hint()
    return f"ssh -L {viewer.port}:127.0.0.1:{viewer.port} USER@THIS-MACHINE"
