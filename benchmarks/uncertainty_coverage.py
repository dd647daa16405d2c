"""Calibration of the 95 % interval of Q: how often it contains the true discharge over seeded runs.

    nice -n 10 .venv/bin/python benchmarks/uncertainty_coverage.py [--scenes oblique,nadir,far_bank]
        [--renders 8] [--variants 5] [--duration 1.5] [--csv /tmp/coverage.csv]

For each scene and each render seed, the clip is rendered with new particles (``seed``) and a new GCP
click error (``click_error_px``, drawn 0.3-1.5 px); then ``--variants`` runs of it each draw new input
errors that a hydrologist would make, and declare their 1-sigma in the project as a user would:
- the water level typed with an error N(0, s_l), s_l drawn 0.005-0.03 m; ``water_level.uncertainty_m = s_l``;
- each taped distance with an error N(0, 0.01 m); ``uncertainty.gcp_distance_sigma_m = 0.01``;
- each surveyed bed elevation with an error N(0, 0.02 m); ``uncertainty.bed_sigma_m = 0.02``;
- GCP picks: the render's click error; ``uncertainty.gcp_px_sigma_px`` = that sigma.
The velocity index is typed exactly as the generator's (0.85), so ``uncertainty.alpha_sigma = 0``: the
benchmark measures everything else (the velocity index uncertainty only widens the interval further).
Variants of one render reuse its PIV field (piv_cache), so they share its PIV error: the figures below
count runs, and renders (independent PIV fields) separately. Only result.json's numbers are needed, so the
plots and files are not written (``write_outputs`` is skipped; the PIV cache still is).

The true discharge is integrated by the generator from the velocity profile it drew (``River.truth()``).
Prints per scene: runs, coverage, median relative width (half-width / Q) and median |error|; then all; then
the same coverage for the ISO 748 and IVE intervals (``uncertainty_standard``, 2σ) beside the Monte Carlo one.
"""

from __future__ import annotations

import argparse
import csv
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from fieldtool.run import outputs
from fieldtool.run.pipeline import run_project
from fieldtool.processing.cross_section import load_cross_section, to_csv_text
from fieldtool.project.model import load_project, save_project
from fieldtool.synthetic import presets, render_scene


def one_scene(name: str, seed: int, duration: float, variants: int, tmp: Path, rows: list[dict]) -> None:
    rng = np.random.default_rng(1000 + seed)
    click = float(rng.uniform(0.3, 1.5))
    d = tmp / f"{name}_{seed}"
    truth = render_scene(presets.get(name, duration_s=duration, seed=seed, click_error_px=click), d)
    base = load_project(truth.project_path)
    cs_exact = load_cross_section(d / base.cross_section.path)
    for k in range(variants):
        p = load_project(truth.project_path)
        s_l = float(rng.uniform(0.005, 0.03))
        p.water_level.value_m = float(truth.water_level_m + rng.normal(0.0, s_l))
        p.water_level.uncertainty_m = s_l
        if p.ortho.method == "distances":
            p.ortho.distances_m = [float(v + rng.normal(0.0, 0.01)) for v in p.ortho.distances_m]
        p.uncertainty.gcp_distance_sigma_m = 0.01
        p.uncertainty.gcp_px_sigma_px = click
        p.uncertainty.alpha_sigma = 0.0
        p.uncertainty.bed_sigma_m = 0.02
        z = cs_exact.elevation + rng.normal(0.0, 0.02, len(cs_exact.elevation))
        cs_file = d / f"cross_section_{k}.csv"
        cs_file.write_text(to_csv_text(type(cs_exact)(cs_exact.station, z)))
        p.cross_section.path = cs_file.name
        save_project(p, d / f"project_{k}.toml")
        p = load_project(d / f"project_{k}.toml")
        t0 = time.perf_counter()
        r = run_project(p, d / "out")
        s = r.summary()
        lo, hi = s["discharge_ci95_m3s"]
        q, qt = s["discharge_m3s"], truth.discharge_m3s
        std = s.get("uncertainty_standard") or {}
        iso, ive = std.get("iso748") or {}, std.get("ive") or {}
        iso_ci, ive_ci = iso.get("ci95_m3s") or [np.nan, np.nan], ive.get("ci95_m3s") or [np.nan, np.nan]
        rows.append({"scene": name, "seed": seed, "variant": k, "click_px": round(click, 3), "level_sigma_m": round(s_l, 4),
                     "q": q, "q_true": qt, "error_pct": 100 * (q - qt) / qt, "lo": lo, "hi": hi,
                     "inside": bool(lo <= qt <= hi), "rel_half_width": 0.5 * (hi - lo) / q,
                     "grade": s["quality"]["grade"], "seconds": round(time.perf_counter() - t0, 2),
                     "iso_inside": bool(iso_ci[0] <= qt <= iso_ci[1]), "iso_rel": iso.get("u95_rel", np.nan),
                     "ive_inside": bool(ive_ci[0] <= qt <= ive_ci[1]), "ive_rel": ive.get("u95_rel", np.nan),
                     "iso_rating": iso.get("rating")})
        print(f"{name:10s} seed {seed:3d} v{k} err {rows[-1]['error_pct']:+6.2f} %  interval ±{100 * rows[-1]['rel_half_width']:.1f} %"
              f"  {'in ' if rows[-1]['inside'] else 'OUT'}  {rows[-1]['grade']}  ISO ±{100 * rows[-1]['iso_rel']:.1f} % "
              f"{'in ' if rows[-1]['iso_inside'] else 'OUT'}  IVE ±{100 * rows[-1]['ive_rel']:.1f} % "
              f"{'in ' if rows[-1]['ive_inside'] else 'OUT'}", flush=True)


def summarize(rows: list[dict]) -> None:
    print(f"\n{len({(r['scene'], r['seed']) for r in rows})} renders (independent particle fields and GCP clicks)")
    print("\n| scenes | runs | coverage of the 95 % interval | median relative half-width | median abs error |")
    print("|---|---|---|---|---|")
    groups = sorted({r["scene"] for r in rows})
    for g in [*groups, "all"]:
        sel = [r for r in rows if g == "all" or r["scene"] == g]
        cov = np.mean([r["inside"] for r in sel])
        w = np.median([r["rel_half_width"] for r in sel])
        e = np.median([abs(r["error_pct"]) for r in sel])
        print(f"| {g} | {len(sel)} | {100 * cov:.1f} % | ±{100 * w:.1f} % | {e:.2f} % |")
    print("\n| scenes | runs | Monte Carlo: coverage, median ± | ISO 748: coverage, median ± | IVE: coverage, median ± |")
    print("|---|---|---|---|---|")
    for g in [*groups, "all"]:
        sel = [r for r in rows if g == "all" or r["scene"] == g]
        cells = []
        for inside, rel in (("inside", "rel_half_width"), ("iso_inside", "iso_rel"), ("ive_inside", "ive_rel")):
            cells.append(f"{100 * np.mean([r[inside] for r in sel]):.1f} %, ±{100 * np.nanmedian([r[rel] for r in sel]):.1f} %")
        print(f"| {g} | {len(sel)} | " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="oblique,nadir,far_bank")
    ap.add_argument("--renders", type=int, default=8, help="render seeds per scene")
    ap.add_argument("--variants", type=int, default=5, help="runs with new input errors per render")
    ap.add_argument("--duration", type=float, default=1.5, help="clip length (s)")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--csv", default="", help="write every run to this CSV")
    args = ap.parse_args()
    outputs.write_outputs = lambda *a, **k: None  # only the summary is needed
    print(f"load average {os.getloadavg()[0]:.1f}")
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.renders):
            for name in args.scenes.split(","):
                one_scene(name, seed, args.duration, args.variants, Path(tmp), rows)
                if args.csv:
                    with open(args.csv, "w", newline="") as fh:
                        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                        w.writeheader()
                        w.writerows(rows)
    summarize(rows)


if __name__ == "__main__":
    main()
