"""A writable matplotlib configuration folder. With an unwritable HOME (a service account, a read-only
home), matplotlib prints two lines of its own ("mkdir -p failed ...", "created a temporary cache
directory ...") before fieldtool says anything; ``MPLCONFIGDIR`` is then set to a folder of this user's
own in the temporary directory, reused from run to run (its font cache too)."""

from __future__ import annotations

import os
import stat
import tempfile


def _usable(folder: str) -> bool:
    """``folder`` is a writable folder, or could be made (its nearest existing parent is a writable folder);
    nothing is created here."""
    path = os.path.abspath(folder)
    while not os.path.lexists(path):
        parent = os.path.dirname(path)
        if parent == path:
            return False
        path = parent
    return os.path.isdir(path) and os.access(path, os.W_OK | os.X_OK)


def ensure_config_dir() -> None:
    """Set ``MPLCONFIGDIR`` when neither it is set nor matplotlib's default folder can be made and written."""
    if os.environ.get("MPLCONFIGDIR"):
        return
    home = os.path.expanduser("~")
    config = os.environ.get("XDG_CONFIG_HOME") or os.path.join(home, ".config")
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(home, ".cache")
    if _usable(os.path.join(config, "matplotlib")) and _usable(os.path.join(cache, "matplotlib")):
        return
    uid = os.getuid() if hasattr(os, "getuid") else 0
    folder = os.path.join(tempfile.gettempdir(), f"fieldtool-matplotlib-{uid}")
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        st = os.lstat(folder)
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != uid:  # someone else's, or a link: one of our own
            folder = tempfile.mkdtemp(prefix="fieldtool-matplotlib-")
    except OSError:
        folder = tempfile.mkdtemp(prefix="fieldtool-matplotlib-")
    os.environ["MPLCONFIGDIR"] = folder
