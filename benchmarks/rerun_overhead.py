"""Cost of rerun logging on a pipeline run: median wall time with and without, as a ratio.

    .venv/bin/python benchmarks/rerun_overhead.py [--project P] [--runs 5] [--end-s S]

Without --project the synthetic demo scene ('oblique') is rendered into a temporary folder.
Runs alternate (without, with) so that drift in machine load hits both alike. Logging saves to an
.rrd file (the default rerun mode). Prints the medians of wall time and of process CPU time (all
threads, rerun's background encoder included; steadier on a shared machine), the overheads, and
the time spent inside the logging calls on the pipeline's thread (the part that delays the run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--project", help="project file (default: render the demo scene)")
    ap.add_argument("--runs", type=int, default=5, help="runs of each kind (default 5)")
    ap.add_argument("--end-s", type=float, default=None, help="shorten the clip to this end time (s)")
    args = ap.parse_args()

    from fieldtool.run.pipeline import run_project
    from fieldtool.project.model import load_project
    from fieldtool.viewer.rerun_log import RerunObserver

    class TimedObserver(RerunObserver):
        """Adds up the time the pipeline's thread spends in each logging call."""

        spent = 0.0

        def _timed(self, name, *a):
            t = time.perf_counter()
            getattr(RerunObserver, name)(self, *a)
            self.spent += time.perf_counter() - t

        def stage(self, *a):
            self._timed("stage", *a)

        def frame(self, *a):
            self._timed("frame", *a)

        def pair(self, *a):
            self._timed("pair", *a)

        def result(self, *a):
            self._timed("result", *a)

    tmp = Path(tempfile.mkdtemp(prefix="rerun_overhead_"))
    if args.project:
        project_path = Path(args.project)
    else:
        from fieldtool.synthetic import presets, render_scene

        print(f"rendering the demo scene into {tmp / 'scene'} ...", flush=True)
        project_path = render_scene(presets.get("oblique"), tmp / "scene").project_path
    project = load_project(project_path)
    if args.end_s is not None:
        project.video.end_s = args.end_s

    plain, logged, cpu_plain, cpu_logged, inside, size = [], [], [], [], [], 0
    for k in range(args.runs):
        t0, c0 = time.perf_counter(), time.process_time()
        run_project(project, None)
        plain.append(time.perf_counter() - t0)
        cpu_plain.append(time.process_time() - c0)
        rrd = tmp / f"run{k}.rrd"
        t0, c0 = time.perf_counter(), time.process_time()
        obs = TimedObserver("save", path=rrd)
        res = run_project(project, None, observer=obs)
        logged.append(time.perf_counter() - t0)
        inside.append(obs.spent / logged[-1])
        cpu_logged.append(time.process_time() - c0)
        size = rrd.stat().st_size
        warn = [w for w in res.warnings if "rerun" in w]
        print(f"run {k + 1}/{args.runs}: without {plain[-1]:.2f} s (cpu {cpu_plain[-1]:.2f} s), "
              f"with rerun {logged[-1]:.2f} s (cpu {cpu_logged[-1]:.2f} s)"
              + (f"  ({warn[0]})" if warn else ""), flush=True)
    a, b = statistics.median(plain), statistics.median(logged)
    ca, cb = statistics.median(cpu_plain), statistics.median(cpu_logged)
    print(f"wall: median without rerun {a:.3f} s, with rerun (save) {b:.3f} s: overhead {100 * (b - a) / a:+.1f} %")
    print(f"cpu:  median without rerun {ca:.3f} s, with rerun (save) {cb:.3f} s: overhead {100 * (cb - ca) / ca:+.1f} %")
    print(f"in logging calls on the pipeline's thread: median {100 * statistics.median(inside):.1f} % of the run")
    print(f"(.rrd {size / 1e6:.1f} MB; {args.runs} runs each, {project_path})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
