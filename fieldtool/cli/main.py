"""`fieldtool` command line: demo, init, run, and the subcommands other modules register.

Every FieldToolError is printed as one message (no traceback) and exits with code 2.
Other modules add subcommands with ``register(subparsers)``; they are listed in ``EXTENSIONS``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

from fieldtool import __version__
from fieldtool.cli.console import end_progress_line, progress_line
from fieldtool.errors import Cancelled, FieldToolError, InputFileError

EXTENSIONS = (
    "fieldtool.tui.commands",
    "fieldtool.viewer.commands",
    "fieldtool.records.commands",
    "fieldtool.cli.commands",
)


BUG_REPORT = "please report it with the command line and the output of the same command with --debug"
def _print_progress(stage: str, done: int, total: int) -> None:
    if total:
        progress_line(f"{stage}: {done}/{total}")


def cmd_run(args: argparse.Namespace) -> int:
    from fieldtool.plots import prerender

    prerender.start()  # the figure process imports matplotlib on the idle core while this one imports the rest
    from fieldtool.run.pipeline import run_project
    from fieldtool.project.model import load_project

    from fieldtool.project.validation import check

    project = load_project(args.project)
    out = Path(args.out) if args.out else Path(args.project).resolve().parent / "out"
    if out.exists() and not out.is_dir():
        raise InputFileError(f"--out {out}: is a file, not a folder; give a folder for the results")
    check(project)  # every key, before any step (run_project checks again: other callers rely on it)
    observer = None
    if args.rerun or project.rerun.mode != "off":
        from fieldtool.viewer.rerun_log import observer_from_args

        observer = observer_from_args(project, args, out)
    t0 = time.perf_counter()
    try:
        result = run_project(project, out, progress=None if args.quiet else _print_progress, observer=observer)
    finally:
        if observer is not None:
            observer.close()
    end_progress_line()
    s = result.summary()
    ci = s.get("discharge_ci95_m3s")
    if not math.isfinite(s["discharge_m3s"]):  # nothing measured (run/unmeasured.py): graded unusable below
        print("discharge     not measured")
    elif ci and None not in ci:
        print(f"discharge     {s['discharge_m3s']:.4f} m3/s  (95 % interval {ci[0]:.4f} - {ci[1]:.4f}, Monte Carlo)")
    else:
        print(f"discharge     {s['discharge_m3s']:.4f} m3/s")
    if s.get("discharge_p05_m3s") is not None:
        print(f"single pairs  {s['discharge_p05_m3s']:.4f} - {s['discharge_p95_m3s']:.4f} m3/s  (5-95 % of the "
              f"{s['n_pairs_with_vectors']} sampled pairs' own discharges; not an interval of Q)")
    print(f"water level   {s['water_level_m']:.3f} m  ({s['water_level_method']}, +/- {s['water_level_uncertainty_m']:.3f} m)")
    print(f"wetted area   {s['wetted_area_m2']:.3f} m2   width {s['wetted_width_m']:.3f} m")
    print(f"mean velocity {s['mean_velocity_ms']:.4f} m/s  (alpha {s['alpha']:.2f})")
    for w in s["warnings"]:
        print(f"warning: {w}")
    if result.piv_reused:
        print("PIV field     reused from the output folder (same clip, corrections and PIV parameters)")
    print(f"results in    {out}  ({time.perf_counter() - t0:.1f} s)")
    if args.record:
        from fieldtool.records.history import record_run

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
    if grade == "unusable":
        print("fieldtool: the measurement is unusable (reasons above); every result file was written", file=sys.stderr)
        return 3
    return 0


def cmd_init(args: argparse.Namespace) -> int:
    from fieldtool.project.template import write_template

    path = write_template(Path(args.dir), force=args.force)
    print(f"wrote {path}; edit it, then: fieldtool run {path}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from fieldtool.run.pipeline import run_project
    from fieldtool.project.model import load_project
    from fieldtool.synthetic import presets, render_scene

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
    ap.add_argument("--debug", action="store_true", help="show the traceback of an internal error")
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
    p.add_argument("--scene", default="oblique", help="scene preset: oblique, nadir, far_bank, a hard one (glints_section, ripples, sparse_patchy, fast_1080p, grazing, compressed, skewed, dropped_frames) or an unseen one (low_light, glare_column, rain, shadows, exposure, debris, standing_waves, drone_4k)")
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


def _os_error_message(e: OSError) -> str:
    """One line for an OSError: the path, what happened, what to do."""
    import errno

    name = e.filename if e.filename is not None else ""
    if e.filename2 is not None:
        name = f"{name} -> {e.filename2}"
    what = e.strerror or type(e).__name__
    fix = {errno.ENOSPC: "free some space or write elsewhere (--out)",
           errno.EDQUOT: "free some space or write elsewhere (--out)",
           errno.EACCES: "check the permissions, or write elsewhere (--out)",
           errno.EPERM: "check the permissions, or write elsewhere (--out)",
           errno.EROFS: "the file system is read-only; write elsewhere (--out)",
           errno.ENOTDIR: "a part of this path is a file, not a folder; give another path",
           errno.EISDIR: "this is a folder; give a file name",
           errno.EEXIST: "a file of this name is in the way; give another path",
           errno.ENAMETOOLONG: "give a shorter path"}.get(e.errno, "check the path")
    return f"{name}: {what}; {fix}" if name else f"{what}; {fix}"


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    from fieldtool.errors import FieldToolWarning

    if issubclass(category, FieldToolWarning):
        end_progress_line()
        print(f"fieldtool: warning: {message}", file=sys.stderr)
    elif os.environ.get("FIELDTOOL_DEBUG"):
        print(f"{filename}:{lineno}: {category.__name__}: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run one command. Exit codes: 0 done (a measurement graded good or doubtful), 2 bad input or a
    file/folder problem (one line naming it), 3 a measurement judged unusable, 1 an internal error
    (one line and a bug-report hint; the traceback only with --debug), 130 interrupted."""
    import warnings

    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or bool(os.environ.get("FIELDTOOL_DEBUG"))
    argv = [a for a in argv if a != "--debug"]
    from fieldtool.errors import FieldToolWarning

    with warnings.catch_warnings():
        warnings.simplefilter("always", FieldToolWarning)
        warnings.showwarning = _show_warning
        try:
            return _main(argv, debug)
        finally:
            end_progress_line()


def _main(argv: list[str], debug: bool) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        return int(args.func(args) or 0)
    except SystemExit:
        raise
    except Cancelled as e:
        end_progress_line()
        print(f"fieldtool: {e}", file=sys.stderr)
        return 130
    except FieldToolError as e:
        end_progress_line()
        print(f"fieldtool: error: {_one_line(str(e))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        end_progress_line()
        print("fieldtool: interrupted", file=sys.stderr)
        return 130
    except OSError as e:
        end_progress_line()
        if debug:
            raise
        print(f"fieldtool: error: {_one_line(_os_error_message(e))}", file=sys.stderr)
        return 2
    except RecursionError:
        end_progress_line()
        if debug:
            raise
        print("fieldtool: error: an input is nested too deeply (lists in lists ...); simplify it", file=sys.stderr)
        return 2
    except MemoryError:
        end_progress_line()
        if debug:
            raise
        print("fieldtool: error: out of memory; use a shorter clip (video.end_s), a larger video.step or a "
              "smaller ROI", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - the top-level guard: never a traceback by default
        end_progress_line()
        if debug:
            raise
        print(f"fieldtool: internal error: {type(e).__name__}: {_one_line(str(e))[:300]}; {BUG_REPORT}",
              file=sys.stderr)
        return 1


def _one_line(text: str) -> str:
    return " ".join(text.split()) if "\n" in text or "\r" in text else text


if __name__ == "__main__":
    sys.exit(main())
