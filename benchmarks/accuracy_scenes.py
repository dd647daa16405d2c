"""Discharge error on the synthetic scenes, for our PIV engine and for OpenPIV on the same frames.

    .venv/bin/python benchmarks/accuracy_scenes.py [--duration 5] [--configs fieldtool:ensemble,fieldtool:median,openpiv:median]

Each config is ENGINE:AVERAGING on the project's 2 passes (OpenPIV: windef 64 -> 32, which has no ensemble).

The true discharge is integrated by the scene generator from the velocity profile it drew; the
pipeline reads only the project file a hydrologist would have written.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from fieldtool.run.pipeline import run_project
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene

SCENES = [("oblique", {}), ("nadir", {}), ("far_bank", {}), ("oblique", {"shake": True}),
          ("oblique", {"glints": True})]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=5.0, help="clip length (s)")
    ap.add_argument("--configs", default="fieldtool:ensemble,fieldtool:median,openpiv:median")
    args = ap.parse_args()
    configs = [c.split(":") for c in args.configs.split(",")]
    print("| scene | true Q (m³/s) | " + " | ".join(f"{e} {a} error | time (s)" for e, a in configs) + " |")
    print("|---|---|" + "---|---|" * len(configs))
    with tempfile.TemporaryDirectory() as tmp:
        for name, flags in SCENES:
            label = "_".join([name, *flags])
            truth = render_scene(presets.get(name, duration_s=args.duration, **flags), Path(tmp) / label)
            cells = []
            for engine, averaging in configs:
                proj = load_project(truth.project_path)
                proj.piv.engine = engine
                proj.piv.averaging = averaging
                if flags.get("glints"):
                    proj.filters = [{"name": "background"}]
                t0 = time.perf_counter()
                q = run_project(proj, None).discharge.discharge_m3s
                dt = time.perf_counter() - t0
                cells.append(f"{100 * (q - truth.discharge_m3s) / truth.discharge_m3s:+.2f} % | {dt:.1f}")
            print(f"| {label} | {truth.discharge_m3s:.3f} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
