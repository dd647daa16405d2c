"""Cost of the robust velocimetry stages next to the PIV engine they feed, on 1280x720 and 1920x1080 frames.

    .venv/bin/python benchmarks/robust_stage_costs.py [--runs 3] [--frames 40]

Per frame: the temporal standardisation (processing/surface.py, whole frame as the box) and the two-pass
ensemble PIV (window 32, overlap 16) on the same frames, timed alternately in one process (medians of
``--runs``); the first look of the frame-gap planning (processing/planning.py, 8 pairs, once per clip); the
zero-peak removal (processing/piv_peaks.py, once per clip on the ensemble planes) as its share of the
ensemble's final step. The texture gate is one comparison per window and pair (not timed).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import piv_synth as syn  # noqa: E402

from fieldtool.processing import piv, planning, surface  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=40)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}; {args.frames} frames; medians of {args.runs} alternating runs")
    print("| frame | standardise (ms/frame) | two-pass ensemble PIV (ms/pair) | standardise / PIV | first look (s, once) "
          "| zero-peak removal (ms, once) |")
    print("|---|---|---|---|---|---|")
    p = piv.PivParams(window_px=32, overlap_px=16, passes=2, averaging="ensemble")
    for h, w in ((720, 1280), (1080, 1920)):
        frames = syn.clip(syn.uniform(3.3, 0.4), h, w, n_frames=args.frames, density=0.02)
        t_std, t_piv, t_look, t_zero = [], [], [], []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            for _f in surface.standardize(iter(frames), None):
                pass
            t_std.append((time.perf_counter() - t0) / len(frames))
            t0 = time.perf_counter()
            piv.analyze(frames, p)
            t_piv.append((time.perf_counter() - t0) / (len(frames) - 1))
            t0 = time.perf_counter()
            plan, rest = planning.first_look(iter(frames), p)
            t_look.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            piv.analyze(frames[:12], replace(p, remove_zero_peak=True))
            with_zero = time.perf_counter() - t0
            t0 = time.perf_counter()
            piv.analyze(frames[:12], p)
            t_zero.append(with_zero - (time.perf_counter() - t0))
        s, q = statistics.median(t_std), statistics.median(t_piv)
        print(f"| {w}x{h} | {1000 * s:.1f} | {1000 * q:.0f} | {s / q:.2f} | {statistics.median(t_look):.2f} | "
              f"{1000 * statistics.median(t_zero):+.0f} |", flush=True)


if __name__ == "__main__":
    main()
