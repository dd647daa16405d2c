"""Subcommands for single steps: `fieldtool calibrate` (lens from a checkerboard video) and
`fieldtool preview` (one frame through the project's filter stack, as PNG)."""

from __future__ import annotations

import argparse

from fieldtool.cli.main import load_measure  # the core, lazily: only when calibrate or preview runs


def _corners(text: str) -> tuple[int, int]:
    try:
        a, b = (int(t) for t in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give inner corners as COLSxROWS, e.g. 9x6") from None
    return a, b


def cmd_calibrate(args: argparse.Namespace) -> int:
    return load_measure().calibrate(args)


def cmd_preview(args: argparse.Namespace) -> int:
    return load_measure().preview_frame(args)


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
