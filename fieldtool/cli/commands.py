"""Subcommands for single steps: `fieldtool calibrate` (lens from a checkerboard video) and
`fieldtool preview` (one frame through the project's filter stack, as PNG)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from fieldtool.errors import InputFileError, ParameterError


def _corners(text: str) -> tuple[int, int]:
    try:
        a, b = (int(t) for t in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give inner corners as COLSxROWS, e.g. 9x6") from None
    return a, b


def cmd_calibrate(args: argparse.Namespace) -> int:
    from fieldtool.processing.calibration import calibrate_video, save_calibration

    from fieldtool.cli.console import end_progress_line, progress_line
    from fieldtool.project.validation import path_problem

    def progress(done: int, total: int) -> None:
        progress_line(f"frames searched: {done}/{total}")

    if not (math.isfinite(args.square_mm) and 0 < args.square_mm <= 10000):
        raise ParameterError(f"--square-mm: {args.square_mm:g} is not a square size; give the side of one square "
                             "in mm (e.g. 25)")
    if not 1 <= args.frames <= 1000:
        raise ParameterError(f"--frames: {args.frames} is out of range; give 1 to 1000 (e.g. 20)")
    msg = path_problem(Path(args.video), "video", kind="video")
    if msg:
        raise InputFileError(msg)
    _check_out_file(args.out, "--out")
    model = calibrate_video(args.video, corners=args.corners, square_mm=args.square_mm, n_frames=args.frames,
                            progress=progress)
    end_progress_line()
    save_calibration(model, args.out)
    fx, fy = model.camera_matrix[0, 0], model.camera_matrix[1, 1]
    fov = model.fov_deg()
    print(f"reprojection error {model.rms_px:.3f} px")
    print(f"fx, fy             {fx:.1f}, {fy:.1f} px; centre {model.camera_matrix[0, 2]:.1f}, {model.camera_matrix[1, 2]:.1f} px")
    print(f"distortion         {', '.join(f'{c:.4f}' for c in model.dist_coeffs.ravel())}")
    print(f"FOV x / y / diag   {fov[0]:.2f} / {fov[1]:.2f} / {fov[2]:.2f} deg")
    print(f"saved              {args.out}")
    if args.project:
        from fieldtool.project.sync import ProjectSync

        # only this key, merged with the TUI's or the viewer's edits; an invalid or read-only file is refused
        ProjectSync(args.project).set_keys({"calibration.path": str(Path(args.out).resolve())})
        print(f"project            {args.project}: calibration.path set")
    return 0


def cmd_preview(args: argparse.Namespace) -> int:
    import cv2

    from fieldtool.run.pipeline import load_inputs, working_frames
    from fieldtool.processing.filters import preview
    from fieldtool.project.model import atomic_write_bytes, load_project

    from fieldtool.project.validation import check

    project = load_project(args.project)
    _check_out_file(args.out, "--out")
    check(project)
    inputs = load_inputs(project)
    if project.filters and any(f.get("name") == "background" for f in project.filters):
        _, frame = next(iter(working_frames(project, inputs)))  # background needs the whole clip
        out = cv2.normalize(frame, None, 0, 255, cv2.NORM_MINMAX).astype("uint8")
    else:
        first = next(iter(inputs.source)).image
        if inputs.lens is not None:
            first = inputs.lens.undistort(first)
        from fieldtool.run.pipeline import roi_and_mask

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


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="lens calibration from a checkerboard video")
    p.add_argument("video", help="checkerboard video")
    p.add_argument("--corners", type=_corners, default=(9, 6), help="inner corners COLSxROWS (default 9x6)")
    p.add_argument("--square-mm", type=float, default=25.0, help="side of one square in mm (default 25)")
    p.add_argument("--frames", type=int, default=20, help="number of parts the video is split in (default 20)")
    p.add_argument("--out", default="calibration.toml", help="calibration file to write")
    p.add_argument("--project", help="also set calibration.path in this project file")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("preview", help="first frame through the project's filter stack, as PNG")
    p.add_argument("project")
    p.add_argument("--out", default="preview.png")
    p.set_defaults(func=cmd_preview)
