"""The one progress line of the CLI on stderr, rewritten in place; anything printed after it
(an error, a warning, a result) starts on its own line."""

from __future__ import annotations

import sys

_state = {"open": False}


def progress_line(text: str) -> None:
    """Rewrite the progress line."""
    print(f"\r  {text}", end="", file=sys.stderr, flush=True)
    _state["open"] = True


def end_progress_line() -> None:
    """End the progress line, if one is open."""
    if _state["open"]:
        print(file=sys.stderr, flush=True)
        _state["open"] = False
