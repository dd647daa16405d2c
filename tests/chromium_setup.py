"""Debian's chromium for the browser tests: installed with apt when missing (never `playwright install`)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def ensure_chromium(timeout_s: float = 900) -> tuple[Path | None, str]:
    """Path of Debian's chromium, installing it with apt-get when missing.

    Returns ``(path, "")`` or ``(None, reason)`` when it cannot be installed (not root and no
    password-less sudo, no apt-get, or apt failed).
    """
    if CHROMIUM.is_file():
        return CHROMIUM, ""
    apt = shutil.which("apt-get")
    if apt is None:
        return None, "chromium is missing and apt-get is not available to install it"
    prefix: list[str] = []
    if os.geteuid() != 0:
        sudo = shutil.which("sudo")
        if sudo is None or subprocess.run([sudo, "-n", "true"], capture_output=True).returncode != 0:
            return None, "chromium is missing and installing it needs root (no password-less sudo)"
        prefix = [sudo, "-n"]
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    for cmd in ([*prefix, apt, "update", "-qq"], [*prefix, apt, "install", "-y", "-qq", "chromium"]):
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None, f"`{' '.join(cmd)}` did not finish in {timeout_s:.0f} s"
        if r.returncode != 0:
            return None, f"`{' '.join(cmd)}` failed: {(r.stderr or r.stdout).strip()[-400:]}"
    if not CHROMIUM.is_file():
        return None, "apt-get installed chromium but /usr/bin/chromium is missing"
    return CHROMIUM, ""
