"""The one progress line of the CLI on stderr. On a terminal it is rewritten in place (``\\r``); written to a
file or a pipe (a log), it is one line per stage and at most one every ``LOG_EVERY_S`` seconds, so a log holds
a few readable lines, not one line of thousands of ``\\r`` updates. Anything printed after it (an error, a
warning, a result) starts on its own line."""

from __future__ import annotations

import sys
import time

LOG_EVERY_S = 5.0  # seconds between two progress lines written to a file

_state: dict = {"open": False, "last": None, "t": 0.0, "stage": None, "pending": None}


def _is_tty() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def progress_line(text: str) -> None:
    """Rewrite the progress line (a terminal), or log it now and then (a file)."""
    if _is_tty():
        print(f"\r  {text}", end="", file=sys.stderr, flush=True)
        _state["open"] = True
        return
    stage = text.split(":", 1)[0]
    now = time.monotonic()
    if stage != _state["stage"] or now - _state["t"] >= LOG_EVERY_S:
        print(f"  {text}", file=sys.stderr, flush=True)
        _state.update(stage=stage, t=now, pending=None)
    else:
        _state["pending"] = text


def end_progress_line() -> None:
    """End the progress line, if one is open (a file: write the last state it skipped)."""
    if _state["open"]:
        print(file=sys.stderr, flush=True)
        _state["open"] = False
    if _state["pending"] is not None:
        print(f"  {_state['pending']}", file=sys.stderr, flush=True)
    _state.update(stage=None, t=0.0, pending=None)
