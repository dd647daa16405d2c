"""Run ``fieldtool`` in a child process, optionally slowed, for the kill and signal tests of the output folder.

Usage: ``python outputs_harness.py FRAME_DELAY_S WRITE_DELAY_S fieldtool-args...``. FRAME_DELAY_S sleeps after each
working frame, WRITE_DELAY_S before each output file and each carried file, so that a kill lands at any moment of
the run, outputs and swap included, whatever the CPU. Not a test module (no ``test_`` prefix).
"""

import io
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

NONDETERMINISTIC = {"result.json", "mean_field.nc"}  # timings and creation times differ between identical runs


def snapshot(folder: Path) -> dict[str, bytes] | None:
    """Relative path -> bytes of every file under ``folder`` (None when it does not exist)."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def verdict(now: dict | None, old: dict, new: dict) -> str:
    """ "old" when ``now`` is the old run byte for byte, "new" when it is the new run (byte for byte but for the
    files every run writes afresh, which must still be the new run's and agree with each other), else what is
    wrong (a mixed folder, a missing one)."""
    if now is None:
        return "the output folder is missing"
    if now == old:
        return "old"
    if set(now) != set(new):
        return f"neither run's files: {sorted(set(now) ^ set(new))} differ from the new run's list"
    for name, data in now.items():
        if name in NONDETERMINISTIC:
            if old.get(name) == data:
                return f"mixed: {name} is the old run's while other files are the new run's"
        elif data != new[name]:
            which = "the old run's" if old.get(name) == data else "neither run's"
            return f"mixed: {name} is {which}"
    summary = json.loads(now["result.json"])
    with np.load(io.BytesIO(now["mean_field.npz"])) as z:
        if float(z["discharge_m3s"]) != summary["discharge_m3s"]:
            return "mixed: result.json and mean_field.npz give different discharges"
    return "new"


def temp_leftovers(parent: Path) -> list[str]:
    """Temporary folders and lock files of runs beside output folders in ``parent``."""
    return sorted(p.name for p in Path(parent).iterdir() if re.match(r"^\..*\.(tmp-|old-|lock$)", p.name))


def _staged_files(parent: Path, pid: int) -> bool:
    """The staging folder of the run ``pid`` beside its output folder already holds a file (the PIV cache or the
    outputs)."""
    for p in Path(parent).iterdir():
        if f".tmp-{pid}-" in p.name and p.is_dir():
            try:
                if any(p.iterdir()):
                    return True
            except OSError:
                pass
    return False


def time_phases(start, parent: Path) -> tuple[float, float]:
    """(whole run, writing phase) in seconds of one run ``start()`` (a Popen) with nothing killed: the writing
    phase runs from the first file in the staging folder to the end."""
    t0 = time.monotonic()
    proc = start()
    first = None
    while proc.poll() is None:
        if first is None and _staged_files(parent, proc.pid):
            first = time.monotonic()
        time.sleep(0.01)
    end = time.monotonic()
    if proc.returncode != 0:
        raise RuntimeError(f"the timed run failed ({proc.returncode}): {proc.stderr.read().decode()[-500:]}")
    return end - t0, end - (first or t0)


def kill_once(start, parent: Path, rng, span: float, write_span: float) -> str:
    """Start a run and ``kill -9`` it: half the time at a moment drawn over the whole run, half the time at a
    moment drawn over its writing phase (the outputs, the carry of old files and the swap). Returns when."""
    proc = start()
    if rng.random() < 0.5:
        at = rng.uniform(0.2, span)
        time.sleep(at)
        what = f"{at:5.2f} s into the run"
    else:
        t0 = time.monotonic()
        while not _staged_files(parent, proc.pid) and proc.poll() is None and time.monotonic() - t0 < 5 * span:
            time.sleep(0.005)
        at = rng.uniform(0.0, write_span)
        time.sleep(at)
        what = f"{at:5.2f} s into the writing"
    proc.kill()
    proc.wait()
    return what


if __name__ == "__main__":
    from fieldtool.cli.main import main
    from fieldtool.run import frames, outdir, outputs

    frame_delay, write_delay = float(sys.argv[1]), float(sys.argv[2])
    if frame_delay > 0:
        streamed = frames.working_frames

        def slow_frames(*args, **kwargs):
            for item in streamed(*args, **kwargs):
                time.sleep(frame_delay)
                yield item

        frames.working_frames = slow_frames
    if write_delay > 0:
        write = outputs.atomic_write_bytes
        carry = outdir._carry

        def slow_write(*args, **kwargs):
            time.sleep(write_delay)
            return write(*args, **kwargs)

        def slow_carry(*args, **kwargs):
            time.sleep(write_delay)
            return carry(*args, **kwargs)

        outputs.atomic_write_bytes = slow_write
        outdir._carry = slow_carry
    sys.exit(main(sys.argv[3:]))
