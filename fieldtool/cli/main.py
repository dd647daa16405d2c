"""`fieldtool` command line: demo, init, run, and the subcommands other modules register.

Every FieldToolError is printed as one message (no traceback) and exits with code 2.
Other modules add subcommands with ``register(subparsers)``; they are listed in ``EXTENSIONS``.
"""

from __future__ import annotations

import argparse
import atexit
import errno
import importlib
import os
import sys
import warnings
from pathlib import Path

from fieldtool import __version__
from fieldtool.cli.console import end_progress_line
from fieldtool.cli.signals import EXIT_TERMINATED, Terminated, terminate_as_interrupt
from fieldtool.errors import Cancelled, FieldToolError, FieldToolWarning
from fieldtool.plots import prerender
from fieldtool.project.template import write_template

EXTENSIONS = (
    "fieldtool.tui.commands",
    "fieldtool.viewer.commands",
    "fieldtool.records.commands",
    "fieldtool.records.station_commands",  # fieldtool station (issue 27)
    "fieldtool.cli.commands",
)


#: commands whose process, started as the program, ends without the interpreter's teardown of every module and
#: object (:func:`_leave`): at 720p the teardown took 0.15-0.17 s after the command returned, 0.03-0.04 s with this
#: (timestamps, 3 runs each); everything the run writes is closed and committed by then
LEAVE_AT_ONCE = frozenset({"run"})

BUG_REPORT = "please report it with the command line and the output of the same command with --debug"


def load_measure():
    """cli.measure, lazy: the one import of the core by the command line (here and in cli.commands). The
    pipeline (numpy, OpenCV, SciPy, about 0.5 s) loads only for a command that measures, and `fieldtool run`
    forks its figure process first."""
    from fieldtool.cli import measure

    return measure


def cmd_run(args: argparse.Namespace) -> int:
    prerender.start()  # the figure process imports matplotlib on the idle core while this one imports the rest
    return load_measure().run(args)


def cmd_demo(args: argparse.Namespace) -> int:
    from fieldtool.cli import demo  # lazy: the synthetic renderer (SciPy integrate/optimize, 1-1.5 s) only here

    return demo.demo(args)


def cmd_init(args: argparse.Namespace) -> int:
    path = write_template(Path(args.dir), force=args.force)
    print(f"wrote {path}; edit it, then: fieldtool run {path}")
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
    p.add_argument(
        "--overlay",
        action="store_true",
        help="also write overlay.mp4: the clip with the vectors, the section and Q drawn on it ([overlay])",
    )
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
    p.add_argument(
        "--scene",
        default="oblique",
        help="scene preset: oblique, nadir, far_bank, a hard one (glints_section, ripples, "
        "sparse_patchy, fast_1080p, grazing, compressed, skewed, dropped_frames) or an unseen one (low_light, "
        "glare_column, rain, shadows, exposure, debris, standing_waves, drone_4k)",
    )
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
    name = e.filename if e.filename is not None else ""
    if e.filename2 is not None:
        name = f"{name} -> {e.filename2}"
    what = e.strerror or type(e).__name__
    fix = {
        errno.ENOSPC: "free some space or write elsewhere (--out)",
        errno.EDQUOT: "free some space or write elsewhere (--out)",
        errno.EACCES: "check the permissions, or write elsewhere (--out)",
        errno.EPERM: "check the permissions, or write elsewhere (--out)",
        errno.EROFS: "the file system is read-only; write elsewhere (--out)",
        errno.ENOTDIR: "a part of this path is a file, not a folder; give another path",
        errno.EISDIR: "this is a folder; give a file name",
        errno.EEXIST: "a file of this name is in the way; give another path",
        errno.ENAMETOOLONG: "give a shorter path",
    }.get(e.errno or 0, "check the path")
    return f"{name}: {what}; {fix}" if name else f"{what}; {fix}"


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    if issubclass(category, FieldToolWarning):
        end_progress_line()
        print(f"fieldtool: warning: {message}", file=sys.stderr)
    elif os.environ.get("FIELDTOOL_DEBUG"):
        print(f"{filename}:{lineno}: {category.__name__}: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run one command. Exit codes: 0 done (a measurement graded good or doubtful), 2 bad input or a
    file/folder problem (one line naming it), 3 a measurement judged unusable, 1 an internal error
    (one line and a bug-report hint; the traceback only with --debug), 130 interrupted (Ctrl-C), 143
    terminated (SIGTERM)."""
    as_program = argv is None  # the process' own command line (the console script, python -m): see _leave
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or bool(os.environ.get("FIELDTOOL_DEBUG"))
    argv = [a for a in argv if a != "--debug"]

    with warnings.catch_warnings():
        warnings.simplefilter("always", FieldToolWarning)
        warnings.showwarning = _show_warning
        try:
            with terminate_as_interrupt():  # SIGTERM: as Ctrl-C, exit 143 (cli.signals)
                code = _main(argv, debug)
        finally:
            end_progress_line()
    if as_program and argv[:1] and argv[0] in LEAVE_AT_ONCE:
        _leave(code)
    return code


def _leave(code: int) -> None:
    """End the process with ``code`` as the interpreter would, less its teardown: the exit handlers run (log
    files, a rerun recording, temporary folders: ``atexit``), stdout and stderr are flushed, then ``os._exit``
    skips freeing every module and object one by one (:data:`LEAVE_AT_ONCE`). The thread pools' workers are idle
    by then (the run joined its work)."""
    atexit._run_exitfuncs()  # CPython's own call at exit (underscored, not public; in the module since 3.0)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more can be said on it
            pass
    os._exit(code)


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
    except Terminated:
        end_progress_line()
        print("fieldtool: terminated", file=sys.stderr)
        return EXIT_TERMINATED
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
        print(
            "fieldtool: error: out of memory; use a shorter clip (video.end_s), a larger video.step or a smaller ROI",
            file=sys.stderr,
        )
        return 1
    except Exception as e:  # noqa: BLE001 - the top-level guard: never a traceback by default
        end_progress_line()
        if debug:
            raise
        print(
            f"fieldtool: internal error: {type(e).__name__}: {_one_line(str(e))[:300]}; {BUG_REPORT}", file=sys.stderr
        )
        return 1


def _one_line(text: str) -> str:
    return " ".join(text.split()) if "\n" in text or "\r" in text else text


if __name__ == "__main__":
    sys.exit(main())
