"""Where a run's CPU goes, and the fastest wall time that CPU allows: is ≥ 3× pyorc reachable without less work?

    PYTHONPATH=. .venv/bin/python benchmarks/cpu_budget.py --clips 720p_8s,1080p_30s,fast_1080p,4k_drone

Per clip (the clips of ``time_to_q.py``, rendered there once), in alternating runs (``--repeats``, medians):

* ``fieldtool run`` with the defaults, in a process that reports its own CPU (user + system, every thread) apart
  from its children's: the figure processes (``plots.prerender``), waited by the run before it exits;
* pyorc at its most accurate setting (``peer_settings.json``) and the decode-only floor, as ``time_to_q.py``
  runs them (their CPU: the process and its children).

Printed: wall s; the run's CPU s and the figures' CPU s; the floor's wall and CPU s; and a bound on this host
(``os.cpu_count()`` cores). A process cannot finish in less wall time than its CPU over the cores, so
``run CPU / cores`` is the fastest wall time the run's work allows, even were the figures free and every stage
perfectly parallel; ``pyorc wall / that`` is the best pyorc ratio without cutting the run's work. Where that
bound is below 3, ≥ 3× pyorc needs less CPU in the run (decoding, standardising, correlating), not more overlap.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import time_to_q as ttq  # noqa: E402

# the run in a process of its own that prints its CPU and its children's once its exit handlers run (the CLI ends
# with os._exit after atexit, and the figure processes are waited by then)
WRAPPER = """
import atexit, json, resource, runpy, sys
def report():
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    print("CPU " + json.dumps({"run": s.ru_utime + s.ru_stime, "children": c.ru_utime + c.ru_stime}), flush=True)
atexit.register(report)
sys.argv = ["fieldtool"] + sys.argv[1:]
runpy.run_module("fieldtool.cli.main", run_name="__main__")
"""


def run_fieldtool(toml: Path, scratch: Path) -> dict:
    """time_to_q.py's run, through WRAPPER: its wall time and discharge, the run's CPU and the figures'."""
    r = ttq.run_fieldtool(toml, scratch, launcher=("-c", WRAPPER))
    cpu = json.loads(next(line for line in r["stdout"].splitlines() if line.startswith("CPU "))[4:])
    return {**r, "run_cpu": cpu["run"], "fig_cpu": cpu["children"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default=os.path.join(tempfile.gettempdir(), "ft_time_to_q"), help="clip folder")
    ap.add_argument("--clips", default="720p_8s,1080p_30s,fast_1080p,4k_drone")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    import compileall

    compileall.compile_dir(str(ttq.REPO / "fieldtool"), quiet=1)  # as time_to_q.py: an installed package's pyc
    cores = os.cpu_count() or 1
    rows = []
    best = ttq.best_settings()
    with tempfile.TemporaryDirectory(prefix="cpu_budget_") as tmp:
        scratch = Path(tmp)
        for c in ttq.clips(Path(args.root), args.clips.split(",")):
            pyorc_job = ttq.pyorc_job(c, best["pyorc"])
            video = c["dir"] / c["spec"].video_name
            ft, py, fl = [], [], []
            for _ in range(args.repeats):  # alternating
                ft.append(run_fieldtool(c["dir"] / "noroi.toml", scratch))
                py.append(ttq.run_peer("pyorc_run.py", pyorc_job))
                fl.append(ttq.run_peer("decode_floor.py", video))

            def med(runs: list[dict], key: str) -> float:
                return float(np.median([r[key] for r in runs]))

            truth = c["truth"]["discharge_m3s"]
            row = {
                "clip": c["name"],
                "ft_s": med(ft, "s"),
                "run_cpu": med(ft, "run_cpu"),
                "fig_cpu": med(ft, "fig_cpu"),
                "pyorc_s": med(py, "s"),
                "floor_s": med(fl, "s"),
                "floor_cpu": med(fl, "cpu"),
                "err": 100.0 * (med(ft, "q") / truth - 1.0),
            }
            row["bound_s"] = row["run_cpu"] / cores
            rows.append(row)
            walls = {k: " ".join(f"{r['s']:.2f}" for r in v) for k, v in (("ft", ft), ("py", py), ("fl", fl))}
            print(f"{c['name']}: fieldtool {walls['ft']} s, pyorc {walls['py']} s, floor {walls['fl']} s")
    print(
        f"\nCPU budget, {cores} cores, {args.repeats} alternating runs, medians, load average "
        f"{os.getloadavg()[0]:.2f} at the end; pyorc at {best['pyorc'][0]} m / {best['pyorc'][1]} px"
    )
    print(
        "| clip | fieldtool s (err) | run CPU s | figures CPU s | floor s (CPU s) | pyorc s | pyorc / ft "
        "| run CPU / cores | best pyorc ratio |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['clip']} | {r['ft_s']:.2f} ({r['err']:+.2f} %) | {r['run_cpu']:.2f} | {r['fig_cpu']:.2f} | "
            f"{r['floor_s']:.2f} ({r['floor_cpu']:.2f}) | {r['pyorc_s']:.2f} | {r['pyorc_s'] / r['ft_s']:.2f}× | "
            f"{r['bound_s']:.2f} | {r['pyorc_s'] / r['bound_s']:.2f}× |"
        )


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    print(f"({time.perf_counter() - t0:.0f} s)")
