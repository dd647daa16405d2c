"""One picking viewer per project: an info file beside the project names the running one.

``.<project file name>.viewer.json`` (e.g. ``.project.toml.viewer.json``) holds the viewer's process id,
port, key (token) and URL, written (mode 0600: the key is a secret) when a viewer starts and removed when it
stops. ``running_viewer(project)`` returns it only when that process is alive and its port answers on the
loopback, so a viewer killed with ``kill -9`` leaves a stale file that is ignored and replaced.
``fieldtool view`` and the TUI's ``ctrl+o`` attach to the running viewer instead of starting a second one
with its own pick state.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass
from pathlib import Path

from fieldtool.run.outdir import pid_alive
from fieldtool.viewer.guard import ssh_hint as _ssh_hint


def info_path(project_path: Path | str) -> Path:
    p = Path(project_path).resolve()
    return p.parent / f".{p.name}.viewer.json"


@dataclass
class RunningViewer:
    """A viewer of this project served by another process (or this one): what the operator needs to
    reach it. The TUI holds one in place of its own viewer: picks reach the TUI through the file."""

    pid: int
    host: str
    port: int
    token: str
    url: str
    in_process: bool = False
    warning: str | None = None
    notes: tuple = ()

    @property
    def ssh_hint(self) -> str:
        return _ssh_hint(self.port)

    @property
    def local_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/{self.token}/"

    # the TUI's calls on a viewer it does not run: the other process watches the file itself
    def set_mode(self, mode) -> None:
        pass

    def reload(self) -> None:
        pass

    def show_image(self, kind: str) -> None:
        raise RuntimeError(
            f"the viewer at {self.url} belongs to another fieldtool (pid {self.pid}); choose the image there"
        )

    def show_field(self, npz_path=None) -> bool:
        return False

    def stop(self) -> None:
        pass


def _answers(port: int, timeout: float = 1.0) -> bool:
    """Whether an HTTP server answers on the loopback port (a plain request for the key-less root, which
    the viewer refuses with 403: an answer, and no half-open connection in its log)."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
            sock.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
            return sock.recv(16).startswith(b"HTTP/")
    except OSError:
        return False


def running_viewer(project_path: Path | str) -> RunningViewer | None:
    """The live viewer of this project named by its info file, or None (none, dead, or not answering)."""
    p = info_path(project_path)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
        rv = RunningViewer(int(d["pid"]), str(d["host"]), int(d["port"]), str(d["token"]), str(d["url"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not pid_alive(rv.pid) or not _answers(rv.port):
        return None
    return rv


def register(project_path: Path | str, host: str, port: int, token: str, url: str) -> Path:
    """Write the info file of the viewer this process now serves (atomic, mode 0600)."""
    p = info_path(project_path)
    tmp = p.with_name(p.name + f".{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump({"pid": os.getpid(), "host": host, "port": port, "token": token, "url": url}, fh)
    os.replace(tmp, p)
    return p


def unregister(project_path: Path | str) -> None:
    """Remove the info file when it names this process."""
    p = info_path(project_path)
    try:
        if int(json.loads(p.read_text(encoding="utf-8")).get("pid", -1)) == os.getpid():
            p.unlink()
    except (OSError, ValueError, AttributeError):
        pass
