"""What the TUI tells the operator about reaching the picking viewer over SSH."""

from __future__ import annotations


def ssh_line(port: int, host: str = "HOST") -> str:
    """The port forward to run on the operator's computer to reach a viewer on ``port`` of the
    machine the TUI runs on (``host``: that machine's SSH name)."""
    try:  # the viewer's own wording, once it provides one
        from ..viewer.server import ssh_forward_line
    except ImportError:
        return f"ssh -L {port}:127.0.0.1:{port} {host}"
    return ssh_forward_line(port)
