"""`fieldtool tui [PROJECT]`: registered into the CLI by fieldtool.cli.main."""

from __future__ import annotations

import argparse


def cmd_tui(args: argparse.Namespace) -> int:
    from fieldtool.tui.app import FieldToolApp  # lazy: textual and the TUI, not for every `fieldtool` command

    app = FieldToolApp(args.project)
    app.run()
    return int(app.return_code or 0)


def register(sub) -> None:
    p = sub.add_parser("tui", help="step-by-step measurement in the terminal (keyboard only, works over SSH)")
    p.add_argument(
        "project",
        nargs="?",
        default="project.toml",
        help="project file or its folder (default ./project.toml; created when missing)",
    )
    p.set_defaults(func=cmd_tui)
