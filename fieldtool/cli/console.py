"""The one progress line of the CLI on stderr. On a terminal it is rewritten in place (``\\r``), at most every
``TTY_EVERY_S`` seconds within a stage (the run's stages report every frame); written to a file or a pipe (a
log), it is one line per stage and at most one every ``LOG_EVERY_S`` seconds, so a log holds a few readable
lines, not one line of thousands of ``\\r`` updates. The last state skipped is written when the line ends.
Anything printed after it (an error, a warning, a result) starts on its own line."""

from __future__ import annotations

import sys
import time

LOG_EVERY_S = 5.0  # seconds between two progress lines written to a file
TTY_EVERY_S = 0.1  # seconds between two rewrites of the line on a terminal, within a stage

_state: dict = {"open": False, "last": None, "t": 0.0, "stage": None, "pending": None}


def _is_tty() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def progress_line(text: str) -> None:
    """Rewrite the progress line (a terminal), or log it now and then (a file). An update within ``TTY_EVERY_S``
    of the stage's last one is only remembered, before stderr is even asked whether it is a terminal."""
    stage = text.split(":", 1)[0]
    now = time.monotonic()
    if stage == _state["stage"] and now - _state["t"] < TTY_EVERY_S:
        _state["pending"] = text
        return
    if _is_tty():
        print(f"\r  {text}", end="", file=sys.stderr, flush=True)
        _state.update(open=True, stage=stage, t=now, pending=None)
        return
    if stage != _state["stage"] or now - _state["t"] >= LOG_EVERY_S:
        print(f"  {text}", file=sys.stderr, flush=True)
        _state.update(stage=stage, t=now, pending=None)
    else:
        _state["pending"] = text


def end_progress_line() -> None:
    """End the progress line, if one is open, with the last state it skipped (a terminal: rewritten in place;
    a file: a line of its own)."""
    pending = _state["pending"]
    if _state["open"]:
        if pending is not None:
            print(f"\r  {pending}", end="", file=sys.stderr)
        print(file=sys.stderr, flush=True)
        _state["open"] = False
    elif pending is not None:
        print(f"  {pending}", file=sys.stderr, flush=True)
    _state.update(stage=None, t=0.0, pending=None)
