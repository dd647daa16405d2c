"""The picking viewer (viser) and the rerun stream. ``ssh_hint(port)`` is the SSH tunnel line."""

from fieldtool.viewer.guard import ssh_hint

__all__ = ["ssh_hint"]
