"""Discharge error of PIV, STIV and their combination on synthetic scenes, and what STIV costs per clip.

    PYTHONPATH=. .venv/bin/python benchmarks/stiv_accuracy.py [--duration 5] [--repeats 3] [--scenes oblique,nadir,sparse]

One run per scene with the project's defaults gives all three discharges (STIV is computed during the
PIV's frame stream; ``result.json`` "stiv": discharge_m3s, discharge_combined_m3s). Cost: runs with
``[stiv] enabled`` true and false alternate in one process; the table gives the median of STIV's own
timer (line sampling + analysis, wall s per clip) and the median wall and CPU-time differences of the
paired runs (CPU time is the steadier figure on a loaded machine).
The true discharge is integrated by the scene generator from the profile it drew.

Scenes: the presets by name; ``sparse`` is ``sparse_patchy`` when fieldtool.synthetic.presets has it,
else the oblique scene with 2 tracers/m² (instead of 20).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from fieldtool.run.pipeline import run_project
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene


def scene_spec(name: str, duration: float):
    if name == "sparse":
        try:
            return "sparse_patchy", presets.get("sparse_patchy", duration_s=duration)
        except Exception:  # noqa: BLE001 - the hard presets may not be merged yet
            return "oblique, 2 tracers/m²", presets.get("oblique", duration_s=duration, particle_density_m2=2.0)
    return name, presets.get(name, duration_s=duration)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=5.0, help="clip length (s)")
    ap.add_argument("--repeats", type=int, default=3, help="paired on/off runs for the cost")
    ap.add_argument("--scenes", default="oblique,nadir,sparse,far_bank")
    ap.add_argument("--method", default=None, help="override [stiv] method (fft | tensor)")
    args = ap.parse_args()
    print(f"load average at start: {os.getloadavg()}")
    print("| scene | true Q (m³/s) | PIV error | STIV error | combined error | STIV s/clip (own timer, median) "
          "| run with - without STIV: wall s, CPU s (medians) | lines analysed |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes.split(","):
            label, spec = scene_spec(name, args.duration)
            truth = render_scene(spec, Path(tmp) / name)
            q0 = truth.discharge_m3s
            own, diff, cpu = [], [], []
            res = None
            for _ in range(args.repeats):
                times, cpus = {}, {}
                for enabled in (True, False):
                    proj = load_project(truth.project_path)
                    proj.stiv.enabled = enabled
                    if args.method:
                        proj.stiv.method = args.method
                    t0, c0 = time.perf_counter(), time.process_time()
                    r = run_project(proj, None)
                    times[enabled] = time.perf_counter() - t0
                    cpus[enabled] = time.process_time() - c0
                    if enabled:
                        res = r
                        own.append(r.stiv["seconds"])
                diff.append(times[True] - times[False])
                cpu.append(cpus[True] - cpus[False])
            st = res.stiv

            def err(q):
                return "n/a" if q is None else f"{100 * (q - q0) / q0:+.2f} %"

            print(f"| {label} | {q0:.3f} | {err(res.discharge.discharge_m3s)} | {err(st['discharge_m3s'])} | "
                  f"{err(st['discharge_combined_m3s'])} | {statistics.median(own):.2f} | "
                  f"{statistics.median(diff):+.2f}, {statistics.median(cpu):+.2f} | {st['n_lines_analysed']} of {st['n_lines']} |", flush=True)
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
