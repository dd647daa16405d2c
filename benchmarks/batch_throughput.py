"""Batch throughput: N demo scenes run one after the other in this process vs. `run_batch` on
local processes (and optionally on a Dask cluster). Prints the wall times and their ratio.

    .venv/bin/python benchmarks/batch_throughput.py                   # 4 scenes, 2 s each, 2 workers
    .venv/bin/python benchmarks/batch_throughput.py --n 8 --workers 4
    .venv/bin/python benchmarks/batch_throughput.py --scheduler tcp://HOST:8786   # also on a cluster

For a cluster, the scene folder (--root) must be on a file system the workers see at the same path.
Not part of the test run.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from fieldtool.records.batch import plan_projects, run_batch


def scenes(root: Path, n: int, duration_s: float) -> list[Path]:
    from fieldtool.synthetic import presets, render_scene

    paths = []
    for i in range(n):
        d = root / f"scene_{i:02d}_{duration_s:g}s"
        if not (d / "project.toml").is_file():
            render_scene(presets.get("oblique", duration_s=duration_s, seed=100 + i), d)
        paths.append(d / "project.toml")
    return paths


def timed(label: str, items, **kw):
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    res = run_batch(items, **kw)
    wall = time.perf_counter() - t0
    cpu = sum(r.cpu_s for r in res.results)  # CPU of the runs themselves (all threads), not of starting workers
    if res.failed:
        raise SystemExit(f"{label}: {len(res.failed)} failed: {[r.error for r in res.failed]}")
    per = [r.seconds for r in res.results]
    print(f"{label:<28} wall {wall:7.2f} s   run cpu {cpu:7.2f} s   per item {min(per):.2f}-{max(per):.2f} s   "
          f"load before {load:.1f}   ({res.executor})")
    return wall, [r.summary["discharge_m3s"] for r in res.results]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=4, help="number of scenes (default 4)")
    ap.add_argument("--duration", type=float, default=2.0, help="clip length in seconds at 30 fps (default 2)")
    ap.add_argument("--workers", type=int, default=2, help="local processes (default 2)")
    ap.add_argument("--scheduler", help="also run on this Dask scheduler (tcp://HOST:PORT)")
    ap.add_argument("--root", help="folder for the scenes and results (default: a temporary folder)")
    args = ap.parse_args()

    root = Path(args.root) if args.root else Path(tempfile.mkdtemp(prefix="ft_batch_bench_"))
    print(f"{args.n} oblique scenes of {args.duration:g} s ({int(args.duration * 30)} frames, 1280x720) in {root}; "
          f"{os.cpu_count()} cores visible")
    paths = scenes(root, args.n, args.duration)

    serial, q_serial = timed("serial (this process)", plan_projects(paths, out_root=root / "out_serial"), workers=1)
    par, q_par = timed(f"local, {args.workers} processes", plan_projects(paths, out_root=root / "out_local"),
                       workers=args.workers)
    assert q_par == q_serial, "the parallel run gave other discharges"
    print(f"throughput ratio (serial wall / {args.workers}-process wall): {serial / par:.2f}")
    if args.scheduler:
        dsk, q_dsk = timed("dask " + args.scheduler, plan_projects(paths, out_root=root / "out_dask"),
                           scheduler=args.scheduler)
        assert q_dsk == q_serial, "the Dask run gave other discharges"
        print(f"throughput ratio (serial wall / Dask wall): {serial / dsk:.2f}")


if __name__ == "__main__":
    main()
