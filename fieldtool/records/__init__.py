"""Records kept across measurements: sites, the measurement history, reports and batch runs.

- :mod:`.sites`: a station's fixed inputs (cross-section, GCPs, lens, ROI, stable regions, default
  parameters) as a folder with a ``site.toml``; a new visit needs only the video and the water level.
- :mod:`.history`: every run in an embedded SQLite database, with reference discharges.
- :mod:`.rating`: the stage-discharge (rating) curve Q = a (h - h0)^b.
- :mod:`.report`: one self-contained HTML (and optional PDF) per measurement.
- :mod:`.batch`: many measurements on local cores or a Dask cluster.

Where things live by default (each can be changed, see :func:`user_data_dir`):
``$XDG_DATA_HOME/fieldtool`` (Linux, falling back to ``~/.local/share/fieldtool``),
``~/Library/Application Support/fieldtool`` (macOS), ``%LOCALAPPDATA%\\fieldtool`` (Windows).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


def user_data_dir() -> Path:
    """The per-user data folder of fieldtool (not created here)."""
    if sys.platform.startswith("win"):
        base = os.environ.get("LOCALAPPDATA") or str(Path.home() / "AppData" / "Local")
        return Path(base) / "fieldtool"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Application Support" / "fieldtool"
    base = os.environ.get("XDG_DATA_HOME") or ""
    return (Path(base) if base and Path(base).is_absolute() else Path.home() / ".local" / "share") / "fieldtool"
