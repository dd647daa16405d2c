"""`fieldtool` command line: demo, init, run, and the subcommands other modules register.

Every FieldToolError is printed as one message (no traceback) and exits with code 2.
Other modules add subcommands with ``register(subparsers)``; they are listed in ``EXTENSIONS``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import threading
import time
from pathlib import Path

from . import __version__
from .errors import Cancelled, FieldToolError

EXTENSIONS = (
    "fieldtool.tui.commands",
    "fieldtool.viewer.commands",
    "fieldtool.records.commands",
    "fieldtool.commands",
)


def _print_progress(stage: str, done: int, total: int) -> None:
    if total:
        print(f"\r  {stage}: {done}/{total}", end="", file=sys.stderr, flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    from .pipeline import run_project
    from .project import load_project

    project = load_project(args.project)
    out = Path(args.out) if args.out else Path(args.project).resolve().parent / "out"
    observer = None
    if args.rerun or project.rerun.mode != "off":
        from .viewer.rerun_log import observer_from_args

        observer = observer_from_args(project, args, out)
    t0 = time.perf_counter()
    try:
        result = run_project(project, out, progress=None if args.quiet else _print_progress, observer=observer)
    finally:
        if observer is not None:
            observer.close()
    if not args.quiet:
        print(file=sys.stderr)
    s = result.summary()
    print(f"discharge     {s['discharge_m3s']:.4f} m3/s  (pairs 5-95 %: {s['discharge_p05_m3s']:.4f} - {s['discharge_p95_m3s']:.4f})")
    print(f"water level   {s['water_level_m']:.3f} m  ({s['water_level_method']}, +/- {s['water_level_uncertainty_m']:.3f} m)")
    print(f"wetted area   {s['wetted_area_m2']:.3f} m2   width {s['wetted_width_m']:.3f} m")
    print(f"mean velocity {s['mean_velocity_ms']:.4f} m/s  (alpha {s['alpha']:.2f})")
    for w in s["warnings"]:
        print(f"warning: {w}")
    if result.piv_reused:
        print("PIV field     reused from the output folder (same clip, corrections and PIV parameters)")
    print(f"results in    {out}  ({time.perf_counter() - t0:.1f} s)")
    if args.record:
        from .records.history import record_run

        mid = record_run(project, s, out, site=args.site or project.site, db=args.db)
        print(f"recorded      history id {mid}")
    if observer is not None and observer.mode == "serve":
        print("rerun: still serving the run (listening on all interfaces); press Ctrl-C to stop", file=sys.stderr)
        threading.Event().wait()  # Ctrl-C ends it: main() catches KeyboardInterrupt
    return 0


def cmd_init(args: argparse.Namespace) -> int:
    from .template import write_template

    path = write_template(Path(args.dir), force=args.force)
    print(f"wrote {path}; edit it, then: fieldtool run {path}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .pipeline import run_project
    from .project import load_project
    from .synthetic import presets, render_scene

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
    report = {"scene": args.scene, "discharge_m3s": q, "true_discharge_m3s": q_true, "error_percent": err,
              "render_s": round(t1 - t0, 2), "pipeline_s": round(t2 - t1, 2)}
    (out / "demo.json").write_text(json.dumps(report, indent=2))
    print(f"computed discharge {q:.4f} m3/s")
    print(f"true discharge     {q_true:.4f} m3/s  (integrated from the generator's velocity profile)")
    print(f"error              {err:+.2f} %")
    print(f"times              render {t1 - t0:.1f} s, pipeline {t2 - t1:.1f} s; results in {out / 'results'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="fieldtool", description="River discharge from a surface video (LSPIV).")
    ap.add_argument("--version", action="version", version=f"fieldtool {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="run every step of a project file headless")
    p.add_argument("project", help="project file (TOML)")
    p.add_argument("--out", help="output folder (default: out/ beside the project file)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--rerun", choices=["save", "connect", "serve"], help="stream to rerun (see README)")
    p.add_argument("--rerun-path", help="rerun: .rrd file for --rerun save")
    p.add_argument("--rerun-url", help="rerun: rerun+http://HOST:PORT/proxy for --rerun connect")
    p.add_argument("--record", action="store_true", help="record the result in the measurement history")
    p.add_argument("--site", help="site name for --record (default: the project's site)")
    p.add_argument("--db", help="history database for --record (default: $FIELDTOOL_DB or the user data folder)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("init", help="write a commented project template into DIR")
    p.add_argument("dir")
    p.add_argument("--force", action="store_true", help="overwrite an existing project.toml")
    p.set_defaults(func=cmd_init)

    p = sub.add_parser("demo", help="render a synthetic river with a known discharge and measure it")
    p.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    p.add_argument("--scene", default="oblique", help="scene preset: oblique, nadir, far_bank, or a hard one (glints_section, ripples, sparse_patchy, fast_1080p, grazing, compressed, skewed, dropped_frames)")
    p.set_defaults(func=cmd_demo)

    for name in EXTENSIONS:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name is None or not name.startswith(e.name):
                raise
            continue
        mod.register(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except Cancelled as e:
        print(f"fieldtool: {e}", file=sys.stderr)
        return 130
    except FieldToolError as e:
        print(f"fieldtool: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fieldtool: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
