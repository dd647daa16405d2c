"""The command line's handlers that need the core: `fieldtool run`, `calibrate` and `preview`.

``cli.main`` and ``cli.commands`` import this module only when one of these commands runs (the parser of every
`fieldtool ...` stays at the standard library), and ``fieldtool run`` only after it has forked the figure process.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from pathlib import Path

import cv2

from fieldtool.cli.console import end_progress_line, progress_line
from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing.calibration import calibrate_video, save_calibration
from fieldtool.processing.filters import preview
from fieldtool.project.model import atomic_write_bytes, load_project
from fieldtool.project.sync import ProjectSync
from fieldtool.project.validation import check, path_problem
from fieldtool.records.history import record_run
from fieldtool.records.report_content import velocities_text
from fieldtool.run.frames import working_frames
from fieldtool.run.geometry import roi_and_mask
from fieldtool.run.inputs import load_inputs
from fieldtool.run.outdir import check_out
from fieldtool.run.pipeline import run_project


def _print_progress(stage: str, done: int, total: int) -> None:
    if total:
        progress_line(f"{stage}: {done}/{total}")


def run(args: argparse.Namespace) -> int:
    """`fieldtool run PROJECT`: every step headless; the figure process was forked by ``cli.main``."""
    project = load_project(args.project)
    out = Path(args.out) if args.out else Path(args.project).resolve().parent / "out"
    check_out(out, project)  # not a file, not read-only, not the project's folder nor one holding an input
    if args.overlay:
        project.overlay.enabled = True  # this run only; the project file is not changed
    check(project)  # every key, before any step (run_project checks again: other callers rely on it)
    observer = None
    if args.rerun or project.rerun.mode != "off":
        from fieldtool.viewer import rerun_log  # lazy: rerun (0.25-0.4 s) only when the run streams to it

        observer = rerun_log.observer_from_args(project, args, out)
    t0 = time.perf_counter()
    try:
        result = run_project(project, out, progress=None if args.quiet else _print_progress, observer=observer)
    finally:
        if observer is not None:
            observer.close()
    end_progress_line()
    s = result.summary()
    ci = s.get("discharge_ci95_m3s")
    q = s.get("discharge_m3s")
    q_ok = isinstance(q, (int, float)) and math.isfinite(q)  # a null discharge is never exit 0 (exit 3 below)
    if not q_ok:
        print("discharge     none (not a finite number)")
    elif ci and None not in ci:
        print(f"discharge     {s['discharge_m3s']:.4f} m3/s  (95 % interval {ci[0]:.4f} - {ci[1]:.4f}, Monte Carlo)")
    else:
        print(f"discharge     {s['discharge_m3s']:.4f} m3/s")
    if s.get("discharge_p05_m3s") is not None:
        print(
            f"single pairs  {s['discharge_p05_m3s']:.4f} - {s['discharge_p95_m3s']:.4f} m3/s  (5-95 % of the "
            f"{s['n_pairs_with_vectors']} sampled pairs' own discharges; not an interval of Q)"
        )
    print(
        f"water level   {s['water_level_m']:.3f} m  ({s['water_level_method']}, "
        f"+/- {s['water_level_uncertainty_m']:.3f} m)"
    )
    print(f"wetted area   {s['wetted_area_m2']:.3f} m2   width {s['wetted_width_m']:.3f} m")
    print(f"mean velocity {s['mean_velocity_ms']:.4f} m/s  (alpha {s['alpha']:.2f})")
    if s.get("stiv"):
        print(f"velocities    {velocities_text(s, 'm3/s')}")
    for w in s["warnings"]:
        print(f"warning: {w}")
    if result.piv_reused:
        print("PIV field     reused from the output folder (same clip, corrections and PIV parameters)")
    ov = s.get("overlay")
    if ov and "overlay" in s["files"]:
        print(
            f"overlay video {out / s['files']['overlay']}  ({ov['frames']} frames + {ov['card_frames']} of the closing "
            f"card, {ov['width_px']}x{ov['height_px']} at {ov['fps']:.3g} fps, {ov['codec']})"
        )
    print(f"results in    {out}  ({time.perf_counter() - t0:.1f} s)")
    if args.record:
        mid = record_run(project, s, out, site=args.site or project.site, db=args.db)
        print(f"recorded      history id {mid}")
    grade = (s.get("quality") or {}).get("grade")
    if grade:
        print(f"quality       {grade}")
        for r in s["quality"]["reasons"]:
            print(f"  {r['severity']}: {r['message']}")
    if observer is not None and observer.mode == "serve":
        print("rerun: still serving the run (listening on all interfaces); press Ctrl-C to stop", file=sys.stderr)
        threading.Event().wait()  # Ctrl-C ends it: main() catches KeyboardInterrupt
    if grade == "unusable" or not q_ok:
        why = "reasons above" if grade == "unusable" else "no finite discharge"
        print(f"fieldtool: the measurement is unusable ({why}); every result file was written", file=sys.stderr)
        return 3
    return 0


def calibrate(args: argparse.Namespace) -> int:
    """`fieldtool calibrate VIDEO`: the lens from a checkerboard video."""

    def progress(done: int, total: int) -> None:
        progress_line(f"frames searched: {done}/{total}")

    if not (math.isfinite(args.square_mm) and 0 < args.square_mm <= 10000):
        raise ParameterError(
            f"--square-mm: {args.square_mm:g} is not a square size; give the side of one square in mm (e.g. 25)"
        )
    if not 1 <= args.frames <= 1000:
        raise ParameterError(f"--frames: {args.frames} is out of range; give 1 to 1000 (e.g. 20)")
    msg = path_problem(Path(args.video), "video", kind="video")
    if msg:
        raise InputFileError(msg)
    _check_out_file(args.out, "--out")
    model = calibrate_video(
        args.video, corners=args.corners, square_mm=args.square_mm, n_frames=args.frames, progress=progress
    )
    end_progress_line()
    save_calibration(model, args.out)
    fx, fy = model.camera_matrix[0, 0], model.camera_matrix[1, 1]
    fov = model.fov_deg()
    print(f"reprojection error {model.rms_px:.3f} px")
    cx, cy = model.camera_matrix[0, 2], model.camera_matrix[1, 2]
    print(f"fx, fy             {fx:.1f}, {fy:.1f} px; centre {cx:.1f}, {cy:.1f} px")
    print(f"distortion         {', '.join(f'{c:.4f}' for c in model.dist_coeffs.ravel())}")
    print(f"FOV x / y / diag   {fov[0]:.2f} / {fov[1]:.2f} / {fov[2]:.2f} deg")
    print(f"saved              {args.out}")
    if args.project:
        # only this key, merged with the TUI's or the viewer's edits; an invalid or read-only file is refused
        ProjectSync(args.project).set_keys({"calibration.path": str(Path(args.out).resolve())})
        print(f"project            {args.project}: calibration.path set")
    return 0


def preview_frame(args: argparse.Namespace) -> int:
    """`fieldtool preview PROJECT`: the first frame through the filter stack, as PNG."""
    project = load_project(args.project)
    _check_out_file(args.out, "--out")
    check(project)
    inputs = load_inputs(project)
    if project.filters and any(f.get("name") == "background" for f in project.filters):
        _, frame = next(iter(working_frames(project, inputs)))  # background needs the whole clip
        # older stubs want an array for dst (OpenCV takes None: a new array); newer ones accept it
        out = cv2.normalize(frame, None, 0, 255, cv2.NORM_MINMAX).astype("uint8")  # type: ignore[call-overload, unused-ignore]
    else:
        first = next(iter(inputs.source)).image
        if inputs.lens is not None:
            first = inputs.lens.undistort(first)
        out = preview(project.filters, first, roi=roi_and_mask(project, inputs)[0])
    ok, buf = cv2.imencode(".png", out)
    if not ok:
        raise ParameterError("filters: the preview could not be encoded as PNG")
    atomic_write_bytes(Path(args.out), buf.tobytes())
    print(f"wrote {args.out}")
    return 0


def _check_out_file(out: str | Path, what: str) -> None:
    """Refuse an output file name that is a folder, or whose folder is a file or is missing."""
    p = Path(out)
    if p.is_dir():
        raise InputFileError(f"{what} {p}: is a folder; give a file name (e.g. {p / 'out.png'})")
    parent = p.parent if str(p.parent) else Path(".")
    if parent.exists() and not parent.is_dir():
        raise InputFileError(f"{what} {p}: {parent} is a file, not a folder")
