"""Which paths are glob patterns: only those where the user wrote ``*`` or ``?`` (square brackets are literal,
as in ``clip [1].mp4`` or ``site [A] 2024/``). No image or video library is imported here."""

from __future__ import annotations

import glob
import os
import re
from pathlib import Path


def is_pattern(path: Path | str) -> bool:
    """True where ``path`` holds ``*`` or ``?`` and no file or folder of that literal name exists."""
    return any(ch in str(path) for ch in "*?") and not os.path.lexists(path)


def literal_glob(pattern: Path | str) -> list[str]:
    """``glob.glob`` with ``*`` and ``?`` as wildcards and ``[``, ``]`` taken literally."""
    return glob.glob(re.sub(r"\[", "[[]", str(pattern)))
