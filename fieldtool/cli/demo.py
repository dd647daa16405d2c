"""`fieldtool demo`: render a synthetic river of known discharge (``fieldtool.synthetic``) and measure it.

``cli.main`` imports this module only for `fieldtool demo`: the renderer's SciPy (integrate, optimize) costs
1-1.5 s to import, which no other command needs.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from fieldtool.project.model import load_project
from fieldtool.run.pipeline import run_project
from fieldtool.synthetic import presets, render_scene


def demo(args: argparse.Namespace) -> int:
    """`fieldtool demo`: render a synthetic scene of known discharge and measure it."""
    out = Path(args.out)
    t0 = time.perf_counter()
    spec = presets.get(args.scene)
    scene_dir = out / "scene"
    print(f"rendering the synthetic '{args.scene}' scene into {scene_dir} ...", flush=True)
    truth = render_scene(spec, scene_dir)
    t1 = time.perf_counter()
    project = load_project(scene_dir / "project.toml")
    print(f"running the pipeline on {scene_dir / 'project.toml'} ...", flush=True)
    result = run_project(project, out / "results")
    t2 = time.perf_counter()
    q, q_true = result.discharge.discharge_m3s, truth.discharge_m3s
    err = 100.0 * (q - q_true) / q_true
    report = {
        "scene": args.scene,
        "discharge_m3s": q,
        "true_discharge_m3s": q_true,
        "error_percent": err,
        "render_s": round(t1 - t0, 2),
        "pipeline_s": round(t2 - t1, 2),
    }
    (out / "demo.json").write_text(json.dumps(report, indent=2))
    print(f"computed discharge {q:.4f} m3/s")
    print(f"true discharge     {q_true:.4f} m3/s  (integrated from the generator's velocity profile)")
    print(f"error              {err:+.2f} %")
    print(f"times              render {t1 - t0:.1f} s, pipeline {t2 - t1:.1f} s; results in {out / 'results'}")
    return 0
