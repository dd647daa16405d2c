"""Discharge error on the first landing's scenes, over several seeds, with optional key overrides.

    nice -n 10 .venv/bin/python benchmarks/old_scenes.py [--duration 5] [--seeds 0,1,2]
        [--scenes oblique,nadir,far_bank,oblique+shake,oblique+glints,oblique+distortion]
        [--set piv.frame_gap=1 --set piv.remove_stationary=false ...] [--keep DIR]

Scenes as the first landing measured them (``benchmarks/accuracy_scenes.py``, ``corrections_e2e.py``):
``oblique+shake`` is stabilised on the bank regions the generator wrote; ``oblique+glints`` runs with the
thesis' background-subtraction filter; ``oblique+distortion`` is calibrated from its rendered checkerboard
video first. The truth is integrated by the generator from the profile it drew.

It runs on any tree of the project (``PYTHONPATH`` chooses which), so the same command measures the tree
before the robust stages and the tree after them; a key given with ``--set`` that the tree does not know is
reported and the row skipped. ``--keep DIR`` keeps the rendered clips (and the lens) between runs.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from fieldtool.run.pipeline import run_project
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene

SCENES = ["oblique", "nadir", "far_bank", "oblique+shake", "oblique+glints", "oblique+distortion"]


def _value(text: str):
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low == "none":
        return None
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text


def _apply(proj, settings: list[str]) -> None:
    for item in settings:
        key, text = item.split("=", 1)
        section, name = key.split(".", 1)
        cfg = getattr(proj, section)
        if not hasattr(cfg, name):
            raise KeyError(key)
        setattr(cfg, name, _value(text))


def _render(label: str, seed: int, duration: float, root: Path):
    name, *flags = label.split("+")
    folder = root / f"{label.replace('+', '_')}_s{seed}_{duration:g}s"
    spec = presets.get(name, duration_s=duration, seed=seed, **{f: True for f in flags})
    return render_scene(spec, folder), folder


def _project(label: str, truth, folder: Path):
    proj = load_project(truth.project_path)
    if label.endswith("+glints"):
        proj.filters = [{"name": "background"}]
    if label.endswith("+distortion"):
        from fieldtool.processing.calibration import calibrate_video, save_calibration
        lens_file = folder / "calibration.toml"
        if not lens_file.exists():
            cal = proj.calibration
            lens = calibrate_video(proj.resolve(cal.checkerboard_video), corners=tuple(cal.corners),
                                   square_mm=cal.square_mm, n_frames=cal.n_frames)
            save_calibration(lens, lens_file)
        proj.calibration.path = "calibration.toml"
    return proj


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=5.0, help="clip length (s)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE override, e.g. piv.frame_gap=1")
    ap.add_argument("--keep", default="", help="folder that keeps the rendered clips between runs")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    import fieldtool
    print(f"tree {Path(fieldtool.__file__).parent.parent}; load average {os.getloadavg()[0]:.1f}; "
          f"clips of {args.duration:g} s; overrides: {', '.join(args.set) or 'none'}")
    print("| scene | " + " | ".join(f"seed {s}" for s in seeds) + " | mean | max abs |")
    print("|---|" + "---|" * (len(seeds) + 2))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        for label in args.scenes.split(","):
            errs = []
            for seed in seeds:
                truth, folder = _render(label, seed, args.duration, root)
                proj = _project(label, truth, folder)
                try:
                    _apply(proj, args.set)
                except KeyError as e:
                    print(f"| {label} | this tree has no key {e} |")
                    break
                t0 = time.process_time()
                q = run_project(proj, None).discharge.discharge_m3s
                errs.append(100 * (q - truth.discharge_m3s) / truth.discharge_m3s)
                print(f"  {label} seed {seed}: {errs[-1]:+.2f} % ({time.process_time() - t0:.1f} CPU s)", flush=True)
            if len(errs) == len(seeds):
                cells = " | ".join(f"{e:+.2f} %" for e in errs)
                print(f"| {label} | {cells} | {sum(errs) / len(errs):+.2f} % | {max(abs(e) for e in errs):.2f} % |",
                      flush=True)


if __name__ == "__main__":
    main()
