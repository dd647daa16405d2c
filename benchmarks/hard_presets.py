"""Discharge error on the hard synthetic presets with default settings, and with each robust stage off.

    .venv/bin/python benchmarks/hard_presets.py [--duration 8] [--seeds 0] [--presets glints_section,ripples]
                                                [--ablation] [--detail] [--scenes-dir DIR]

The true discharge is integrated by the generator from the profile it drew; the pipeline reads only the
project file a hydrologist would have written. ``--ablation`` reruns each preset with one stage off at a time
(see ABLATIONS); ``--detail`` prints the measured and true surface velocity of every subsection.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from fieldtool.run.pipeline import run_project
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene

#: one robust stage off at a time: label -> changes to the project's [piv] table
ABLATIONS: dict[str, dict] = {
    "no standardisation": {"remove_stationary": False},
    "no zero-peak removal": {"remove_zero_peak": False},
    "frame gap 1": {"frame_gap": 1},
    "no upstream rejection": {"reject_upstream": False},
    "all off (before)": {"remove_stationary": False, "remove_zero_peak": False, "frame_gap": 1, "reject_upstream": False},
}


def true_subsection_velocity(spec, dres) -> np.ndarray:
    """True surface velocity normal to the section (m/s) at each subsection's mid-station."""
    r = spec.river
    c = np.cos(np.radians(spec.section_skew_deg))
    s_mid = 0.5 * (dres.station_from + dres.station_to) * c  # cross-section stations run along the section
    return r.surface_velocity(s_mid) * c


def run_one(project_path: Path, changes: dict, spec, detail: bool, q_true: float) -> tuple[float, str, str, float]:
    """Discharge, grade, 95 % interval (and whether it holds the truth) and run time of one configuration."""
    proj = load_project(project_path)
    for k, v in changes.items():
        setattr(proj.piv, k, v)
    t0 = time.perf_counter()
    res = run_project(proj, None)
    dt = time.perf_counter() - t0
    q = res.discharge.discharge_m3s
    summ = res.summary()
    grade = (summ.get("quality") or {}).get("grade", "-")
    ci = summ.get("discharge_ci95_m3s")
    ci_txt = "-"
    if ci and all(v is not None for v in ci):
        ci_txt = f"[{ci[0]:.2f}, {ci[1]:.2f}] {'holds' if ci[0] <= q_true <= ci[1] else 'misses'}"
    if detail:
        d = res.discharge
        vt = true_subsection_velocity(spec, d)
        print("    sub  measured  true   filled")
        for i, (vm, v0, f) in enumerate(zip(d.surface_velocity_ms, vt, d.velocity_filled)):
            print(f"    {i:3d} {vm:8.3f} {v0:7.3f}  {'filled' if f else ''}")
        for w in res.warnings:
            print("    warning:", w)
        print("    robust:", res.robust)
    return q, grade, ci_txt, dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=8.0, help="clip length (s)")
    ap.add_argument("--seeds", default="0", help="comma-separated scene seeds")
    ap.add_argument("--presets", default=",".join(presets.HARD_NAMES))
    ap.add_argument("--ablation", action="store_true", help="also run with each robust stage off")
    ap.add_argument("--detail", action="store_true", help="per-subsection velocities")
    ap.add_argument("--scenes-dir", default=None, help="keep rendered scenes here (reused when present)")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}; clips {args.duration:g} s")
    configs = [("default", {})] + (list(ABLATIONS.items()) if args.ablation else [])
    print("| preset | seed | true Q (m³/s) | " + " | ".join(f"{label} error" for label, _ in configs)
          + " | grade (default) | 95 % interval (default) | time (s) |")
    print("|---|---|---|" + "---|" * len(configs) + "---|---|---|")
    tmp = tempfile.TemporaryDirectory()
    root = Path(args.scenes_dir) if args.scenes_dir else Path(tmp.name)
    for name in args.presets.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            spec = presets.get(name, duration_s=args.duration, seed=seed)
            d = root / f"{name}_s{seed}_{args.duration:g}"
            if (d / "truth.json").is_file() and (d / "project.toml").is_file():
                import json

                q_true = json.loads((d / "truth.json").read_text())["discharge_m3s"]
            else:
                q_true = render_scene(spec, d).discharge_m3s
            cells, grade, ci, t_def = [], "-", "-", 0.0
            for label, changes in configs:
                q, g, c, dt = run_one(d / "project.toml", changes, spec, args.detail and label == "default", q_true)
                if label == "default":
                    grade, ci, t_def = g, c, dt
                cells.append(f"{100 * (q - q_true) / q_true:+.1f} %")
            print(f"| {name} | {seed} | {q_true:.3f} | " + " | ".join(cells) + f" | {grade} | {ci} | {t_def:.1f} |",
                  flush=True)
    tmp.cleanup()


if __name__ == "__main__":
    main()
