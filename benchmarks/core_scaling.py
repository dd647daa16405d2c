"""How fieldtool's and pyorc's times scale with the cores: the same clips on 1, 2, ... cores, in alternating runs.

    PYTHONPATH=. .venv/bin/python benchmarks/core_scaling.py --clips 720p_8s,fast_1080p --repeats 3
    PYTHONPATH=. .venv/bin/python benchmarks/core_scaling.py --cores 1,2 --clips 720p_8s,1080p_30s,fast_1080p,4k_drone

The clips, projects and contestants are ``time_to_q.py``'s (fieldtool with its defaults on the clip without a
ROI, pyorc at its most accurate setting of the sweep, PyAV decoding every frame: the floor). Every repeat runs each
contestant once at each core count, in turn (this process' CPU affinity, which a child inherits, set to the first
N cores before each run and restored after), so a host that slows down within the hour slows every cell alike.
Medians over the repeats.

Printed per clip and core count: the median wall time (s) and CPU time (s) of each contestant, pyorc / fieldtool
(the ratio of medians and the median of the per-run ratios) and fieldtool / the floor. Then, per contestant, the
fit of Amdahl's law to the medians, ``T(n) = serial + parallel / n`` (least squares; exact through two core
counts): the seconds that no number of cores shortens, and the ratio the fit gives at 4 and 8 cores and at any
number. That last line is an extrapolation from the cores measured here, not a measurement, and says so.
Not part of the test run.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import time_to_q as ttq  # noqa: E402

#: core counts the fit extrapolates to (printed as such, never as measured)
EXTRAPOLATE = (4, 8)


def on_cores(n: int, allowed: list[int], run):
    """``run()`` with this process (and so the child it starts) on the first ``n`` of ``allowed`` cores."""
    ttq.limit_cores(n)
    try:
        return run()
    finally:
        os.sched_setaffinity(0, allowed)


def amdahl(counts: list[int], times: list[float]) -> tuple[float, float]:
    """(serial s, parallel s) of ``T(n) = serial + parallel / n`` fitted to the medians (least squares)."""
    a = np.column_stack([np.ones(len(counts)), 1.0 / np.asarray(counts, float)])
    (serial, parallel), *_ = np.linalg.lstsq(a, np.asarray(times, float), rcond=None)
    return float(serial), float(parallel)


def scale(c: dict, counts: list[int], repeats: int, scratch: Path, allowed: list[int]) -> None:
    best = ttq.best_settings()
    contestants = {
        "fieldtool": lambda: ttq.run_fieldtool(c["dir"] / "noroi.toml", scratch),
        "pyorc": lambda: ttq.run_peer("pyorc_run.py", ttq.pyorc_job(c, best["pyorc"])),
        "decode only (PyAV)": lambda: ttq.run_peer("decode_floor.py", c["dir"] / c["spec"].video_name),
    }
    runs: dict[tuple[str, int], list[dict]] = {(k, n): [] for k in contestants for n in counts}
    load0 = os.getloadavg()[0]
    for _ in range(repeats):  # alternating: each repeat runs every contestant on every core count, in turn
        for n in counts:
            for name, run in contestants.items():
                runs[name, n].append(on_cores(n, allowed, run))
    med = {key: float(np.median([r["s"] for r in rs])) for key, rs in runs.items()}
    cpu = {key: float(np.median([r["cpu"] for r in rs])) for key, rs in runs.items()}
    print(
        f"\n== {c['name']}: {repeats} alternating runs on {', '.join(map(str, counts))} cores, pyorc at "
        f"{best['pyorc'][0]} m / {best['pyorc'][1]} px; load average {load0:.2f} before, "
        f"{os.getloadavg()[0]:.2f} after\n"
        "| cores | fieldtool s (CPU s) | pyorc s (CPU s) | floor s | pyorc / fieldtool (per run) | fieldtool / floor |"
        "\n|---|---|---|---|---|---|"
    )
    for n in counts:
        per = np.median([p["s"] / f["s"] for p, f in zip(runs["pyorc", n], runs["fieldtool", n], strict=True)])
        print(
            f"| {n} | {med['fieldtool', n]:.2f} ({cpu['fieldtool', n]:.1f}) | {med['pyorc', n]:.2f} "
            f"({cpu['pyorc', n]:.1f}) | {med['decode only (PyAV)', n]:.2f} | "
            f"{med['pyorc', n] / med['fieldtool', n]:.2f}x ({per:.2f}x) | "
            f"{med['fieldtool', n] / med['decode only (PyAV)', n]:.2f}x |"
        )
    if len(counts) < 2:
        return
    fit = {k: amdahl(counts, [med[k, n] for n in counts]) for k in ("fieldtool", "pyorc")}
    for k, (s, p) in fit.items():
        print(f"{k}: T(n) = {s:.2f} s + {p:.2f} s / n (Amdahl's law through the medians)")
    (fs, fp), (ps, pp) = fit["fieldtool"], fit["pyorc"]
    at = ", ".join(f"{n} cores {(ps + pp / n) / (fs + fp / n):.2f}x" for n in EXTRAPOLATE)
    limit = f"{ps / fs:.2f}x" if fs > 0 else "unbounded"
    print(f"pyorc / fieldtool extrapolated by the fits, not measured: {at}, any number of cores {limit}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=os.path.join(tempfile.gettempdir(), "ft_time_to_q"), help="clip folder")
    ap.add_argument("--clips", default="720p_8s,fast_1080p")
    ap.add_argument("--cores", help="core counts, comma-separated (default: 1 to all this process may use)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    allowed = sorted(os.sched_getaffinity(0))
    try:
        counts = [int(v) for v in args.cores.split(",")] if args.cores else list(range(1, len(allowed) + 1))
    except ValueError:
        ap.error(f"--cores {args.cores!r}: give whole numbers separated by commas, e.g. 1,2")
    if not counts or any(not 1 <= n <= len(allowed) for n in counts):
        ap.error(f"--cores {args.cores}: this machine lets the benchmark use 1 to {len(allowed)} cores")
    ttq.byte_compile()
    with tempfile.TemporaryDirectory(prefix="core_scaling_") as tmp:
        for c in ttq.clips(Path(args.root), args.clips.split(",")):
            scale(c, sorted(set(counts)), args.repeats, Path(tmp), allowed)


if __name__ == "__main__":
    main()
