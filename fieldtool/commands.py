"""Subcommands for single steps: `fieldtool calibrate` (lens from a checkerboard video) and
`fieldtool preview` (one frame through the project's filter stack, as PNG)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import ParameterError


def _corners(text: str) -> tuple[int, int]:
    try:
        a, b = (int(t) for t in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give inner corners as COLSxROWS, e.g. 9x6") from None
    return a, b


def cmd_calibrate(args: argparse.Namespace) -> int:
    from .processing.calibration import calibrate_video, save_calibration

    def progress(done: int, total: int) -> None:
        print(f"\r  frames searched: {done}/{total}", end="", file=sys.stderr, flush=True)

    model = calibrate_video(args.video, corners=args.corners, square_mm=args.square_mm, n_frames=args.frames,
                            progress=progress)
    print(file=sys.stderr)
    save_calibration(model, args.out)
    fx, fy = model.camera_matrix[0, 0], model.camera_matrix[1, 1]
    fov = model.fov_deg()
    print(f"reprojection error {model.rms_px:.3f} px")
    print(f"fx, fy             {fx:.1f}, {fy:.1f} px; centre {model.camera_matrix[0, 2]:.1f}, {model.camera_matrix[1, 2]:.1f} px")
    print(f"distortion         {', '.join(f'{c:.4f}' for c in model.dist_coeffs.ravel())}")
    print(f"FOV x / y / diag   {fov[0]:.2f} / {fov[1]:.2f} / {fov[2]:.2f} deg")
    print(f"saved              {args.out}")
    if args.project:
        from .project import load_project, save_project

        proj = load_project(args.project)
        proj.calibration.path = str(Path(args.out).resolve())
        save_project(proj, args.project)
        print(f"project            {args.project}: calibration.path set")
    return 0


def cmd_preview(args: argparse.Namespace) -> int:
    import cv2

    from .pipeline import load_inputs, working_frames
    from .processing.filters import preview
    from .project import atomic_write_bytes, load_project

    project = load_project(args.project)
    inputs = load_inputs(project)
    if project.filters and any(f.get("name") == "background" for f in project.filters):
        _, frame = next(iter(working_frames(project, inputs)))  # background needs the whole clip
        out = cv2.normalize(frame, None, 0, 255, cv2.NORM_MINMAX).astype("uint8")
    else:
        first = next(iter(inputs.source)).image
        if inputs.lens is not None:
            first = inputs.lens.undistort(first)
        from .pipeline import roi_and_mask

        out = preview(project.filters, first, roi=roi_and_mask(project, inputs)[0])
    ok, buf = cv2.imencode(".png", out)
    if not ok:
        raise ParameterError("filters: the preview could not be encoded as PNG")
    atomic_write_bytes(Path(args.out), buf.tobytes())
    print(f"wrote {args.out}")
    return 0


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
