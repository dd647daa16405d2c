"""The fuzz table: every key of the project file (the key table of docs/keys.md is generated from the same
dataclasses) x bad values, broken files, and broken inputs to the other subcommands; and the
checks every case must pass: exit 0/2/3 (2 where the value cannot be right), one line per error,
no traceback, the project file's bytes unchanged, no partial output folder (a folder that held a
run still holds that run, or a complete new one), strict JSON.

Used by ``tests/cli/test_fuzz.py`` (a bounded sample) and ``benchmarks/fuzz_all.py`` (every case).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import os
import shutil
import subprocess
import sys
import tomllib
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w


@dataclass
class Raw:
    """A value written into the TOML text as is (for what tomli_w cannot write: deep nesting)."""

    text: str


@dataclass
class Case:
    id: str
    key: str | None = None  # dotted key set to value ("" = none)
    value: Any = None
    must_refuse: bool = True  # exit 2 is the only right answer
    setup: Callable[[Path, Path], list[str]] | None = None  # (case folder, project) -> argv (subprocess)
    command: bool = False  # a case of another subcommand (argv from setup)


@dataclass
class Outcome:
    case: Case
    rc: int
    stderr: str
    traceback: bool = False
    multi_line: bool = False
    damaged_project: bool = False
    partial_output: bool = False
    non_json: bool = False
    wrong_code: bool = False
    hang: bool = False

    @property
    def ok(self) -> bool:
        return not (
            self.traceback
            or self.multi_line
            or self.damaged_project
            or self.partial_output
            or self.non_json
            or self.wrong_code
            or self.hang
        )


# ---------------------------------------------------------------------------------------------
# TOML text with Raw values


def _toml_value(v: Any) -> str:
    if isinstance(v, Raw):
        return v.text
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return tomli_w.dumps({"k": v}).split("=", 1)[1].strip()


def to_toml(data: dict) -> str:
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def with_value(data: dict, key: str, value: Any) -> dict:
    d = json.loads(json.dumps(data))
    *head, last = key.split(".")
    node = d
    for h in head:
        node = node.setdefault(h, {})
    node[last] = value
    return d


# ---------------------------------------------------------------------------------------------
# the table


NESTED = Raw("[" * 5000 + "]" * 5000)


def _bad_values(tp: Any, key: str, full: bool) -> list[tuple[str, Any, bool]]:
    """(label, value, must_refuse) for a key of type ``tp``."""
    origin = typing.get_origin(tp)
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if origin in (typing.Union, __import__("types").UnionType) and args:
        tp = args[0]
        origin = typing.get_origin(tp)
    huge_list = [1.0] * 200_001
    if tp is float:
        out = [
            ("type", "abc", True),
            ("nan", math.nan, True),
            ("inf", math.inf, True),
            ("-inf", -math.inf, True),
            ("huge", 1e308, True),
            ("-huge", -1e308, True),
            ("negative", -1.0, False),
            ("zero", 0.0, False),
            ("bool", True, True),
            ("list", [1.0], True),
        ]
    elif tp is int:
        out = [
            ("type", "abc", True),
            ("float", 1.5, True),
            ("huge", 2**62, True),
            ("-huge", -(2**62), True),
            ("negative", -1, False),
            ("zero", 0, False),
            ("bool", True, True),
        ]
    elif tp is bool:
        out = [("type", "yes", True), ("int", 1, True)]
    elif tp is str:
        out = [
            ("type", 12, True),
            ("empty", "", False),
            ("long", "x" * 5000, True),
            ("newline", "a\nb", True),
            ("nul", "a\x00b", True),
            ("table", {"a": 1}, True),
            ("unicode", "Mesure à l'écluse ✓", False),
        ]
        if key.endswith(("path", "video", "image1", "image2")):
            out += [
                ("parent", "../../../../nonexistent/x", False),
                ("proc", "/proc/self/status", False),
                ("dev", "/dev/zero", True),
                ("dir", "/", False),
            ]
    elif origin is list:
        (item,) = typing.get_args(tp) or (Any,)
        out = [("type", "x", True), ("empty", [], False), ("nested", NESTED, True), ("strings", ["a", "b"], True)]
        if typing.get_origin(item) is list:
            out += [
                ("ragged", [[1.0], [2.0, 3.0, 4.0]], True),
                ("nan", [[math.nan, 1.0]] * 4, True),
                ("huge", [[1e308, 1e308]] * 4, True),
                ("flat", [1.0, 2.0], True),
                ("deep", [[[1.0, 2.0]]], True),
                ("coincident", [[100.0, 100.0]] * 4, False),
            ]
        elif item is dict or typing.get_origin(item) is dict:
            out += [
                ("unknown", [{"name": "nope"}], True),
                ("no-name", [{}], True),
                ("nan-param", [{"name": "clahe", "clip_limit": math.nan}], True),
                ("bg-201", [{"name": "background", "method": "median", "samples": 201}], False),
                ("nested-param", [{"name": "clahe", "clip_limit": NESTED}], True),
            ]
        else:
            out += [
                ("nan", [math.nan] * 6, True),
                ("inf", [math.inf] * 6, True),
                ("huge", [1e308] * 6, True),
                ("ragged", [[1.0], [2.0, 3.0]], True),
                ("one", [1.0], False),
            ]
        if full:
            out.append(("long", huge_list, True))
    else:
        out = [("type", "abc", True)]
    return out


def key_cases(full: bool = True) -> list[Case]:
    """Every key of the project x its bad values."""
    from fieldtool.project.model import Project

    cases = []
    hints = typing.get_type_hints(Project)
    proj = Project()
    for f in dataclasses.fields(Project):
        if not f.metadata.get("saved", True):
            continue
        val = getattr(proj, f.name)
        if dataclasses.is_dataclass(val):
            sub = typing.get_type_hints(type(val))
            for sf in dataclasses.fields(val):
                k = f"{f.name}.{sf.name}"
                cases += [Case(f"{k}={label}", k, v, refuse) for label, v, refuse in _bad_values(sub[sf.name], k, full)]
        else:
            cases += [
                Case(f"{f.name}={label}", f.name, v, refuse)
                for label, v, refuse in _bad_values(hints[f.name], f.name, full)
            ]
            cases.append(Case(f"{f.name}=table", f.name, {"a": 1}, True))
    cases.append(Case("unknown-key", "piv.windoww", 3, True))
    return cases


def geometry_cases(gcp: list[list[float]]) -> list[Case]:
    """Degenerate picks of the demo's GCPs."""
    p1, p2, p3, p4 = gcp
    mid = [(p1[0] + p2[0]) / 2, (p1[1] + p2[1]) / 2]
    return [
        Case("gcp-collinear", "ortho.gcp_px", [p1, p2, mid, p4], True),
        Case("gcp-coincident", "ortho.gcp_px", [p1, p2, p3, p1], True),
        Case("gcp-order-1324", "ortho.gcp_px", [p1, p3, p2, p4], False),  # helper `quality` refuses it
        Case("world-collinear", "ortho.gcp_world_m", [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 5.0]], False),
        Case("roi-degenerate", "roi.rect_px", [500.0, 300.0, 503.0, 600.0], True),
        Case("section-one-point", "section.points_px", [[700.0, 400.0], [700.0, 400.0]], True),
        Case("max-velocity-0", "piv.max_velocity_ms", 0.0, True),
    ]


def _write(path: Path, data: bytes) -> None:
    path.write_bytes(data)


def file_cases(full: bool = True) -> list[Case]:
    """Broken files: the project file, the video, the cross-section (run in a subprocess)."""

    def proj_edit(fn):
        def setup(d: Path, proj: Path) -> list[str]:
            fn(d, proj)
            return ["run", str(proj), "--out", str(d / "out"), "--quiet"]

        return setup

    def set_video(content: bytes | None = None, kind: str = "file"):
        def fn(d: Path, proj: Path):
            v = d / "broken.mp4"
            if kind == "fifo":
                os.mkfifo(v)
            elif kind == "dir":
                v.mkdir()
            elif content is not None:
                v.write_bytes(content)
            txt = proj.read_text(encoding="utf-8").replace('path = "river.mp4"', 'path = "broken.mp4"')
            proj.write_text(txt, encoding="utf-8")

        return fn

    def truncated_video(d: Path, proj: Path):
        data = (d / "river.mp4").read_bytes()
        (d / "river.mp4").unlink()  # a hard link to the scene's clip: never truncate that one
        (d / "river.mp4").write_bytes(data[: len(data) // 3])

    def set_xs(content: bytes):
        def fn(d: Path, proj: Path):
            (d / "cross_section.csv").write_bytes(content)

        return fn

    def proj_bytes(fn_bytes):
        def fn(d: Path, proj: Path):
            proj.write_bytes(fn_bytes(proj.read_bytes()))

        return fn

    def proj_fifo(d: Path, proj: Path):
        proj.unlink()
        os.mkfifo(proj)

    def proj_missing(d: Path, proj: Path):
        proj.unlink()

    def proj_dir(d: Path, proj: Path):
        proj.unlink()
        proj.mkdir()

    def latin(b):
        return b.decode().replace('name = "synthetic oblique"', 'name = "Mesure à l\'écluse"').encode("latin-1")

    cases = [
        Case("project-missing", setup=proj_edit(proj_missing)),
        Case("project-empty", setup=proj_edit(proj_bytes(lambda b: b""))),
        Case("project-truncated", setup=proj_edit(proj_bytes(lambda b: b[: len(b) // 2]))),
        Case("project-fifo", setup=proj_edit(proj_fifo)),
        Case("project-dir", setup=proj_edit(proj_dir)),
        Case("project-binary", setup=proj_edit(proj_bytes(lambda b: bytes(range(256)) * 8))),
        Case("project-latin1", setup=proj_edit(proj_bytes(latin)), must_refuse=False),
        Case("project-utf16", setup=proj_edit(proj_bytes(lambda b: b.decode().encode("utf-16"))), must_refuse=False),
        Case("project-utf8-bom", setup=proj_edit(proj_bytes(lambda b: b"\xef\xbb\xbf" + b)), must_refuse=False),
        Case("video-missing", setup=proj_edit(set_video())),
        Case("video-empty", setup=proj_edit(set_video(b""))),
        Case("video-text", setup=proj_edit(set_video(b"not a video\n" * 100))),
        Case("video-fifo", setup=proj_edit(set_video(kind="fifo"))),
        Case("video-dir-empty", setup=proj_edit(set_video(kind="dir"))),
        Case("video-truncated", setup=proj_edit(truncated_video), must_refuse=False),
        Case("xs-empty", setup=proj_edit(set_xs(b""))),
        Case("xs-binary", setup=proj_edit(set_xs(bytes(range(256)) * 4))),
        Case(
            "xs-latin1",
            setup=proj_edit(set_xs("# profil mesuré\n0,11\n1,10\n2,9\n10,9\n11,10\n12,11\n".encode("latin-1"))),
            must_refuse=False,
        ),
    ]
    return cases


def command_cases() -> list[Case]:
    """Other subcommands with broken inputs (subprocess; the argv comes from setup)."""

    def c(id_, fn, refuse=True):
        return Case(id_, setup=fn, command=True, must_refuse=refuse)

    def levels(content: bytes):
        def fn(d, proj):
            (d / "levels.csv").write_bytes(content)
            (d / "videos").mkdir()
            return [
                "batch",
                "--site",
                "nosuchsite",
                "--videos",
                str(d / "videos"),
                "--levels",
                str(d / "levels.csv"),
                "--no-history",
                "--sites",
                str(d / "sites"),
            ]

        return fn

    def report_json(content: bytes):
        def fn(d, proj):
            (d / "res").mkdir()
            (d / "res" / "result.json").write_bytes(content)
            return ["report", str(d / "res"), "--db", str(d / "h.db")]

        return fn

    def batch_same_out(d, proj):
        return ["batch", str(proj), str(proj), "--no-history"]

    return [
        c("run-out-is-file", lambda d, p: (d / "f").write_text("x") and ["run", str(p), "--out", str(d / "f")]),
        c("run-out-proc", lambda d, p: ["run", str(p), "--out", "/proc/fieldtool_fuzz"]),
        c(
            "run-out-under-file",
            lambda d, p: (d / "f").write_text("x") and ["run", str(p), "--out", str(d / "f" / "o")],
        ),
        c("calibrate-out-dir", lambda d, p: ["calibrate", str(d / "river.mp4"), "--out", str(d)]),
        c("calibrate-square-inf", lambda d, p: ["calibrate", str(d / "river.mp4"), "--square-mm", "inf"]),
        c("calibrate-square-nan", lambda d, p: ["calibrate", str(d / "river.mp4"), "--square-mm", "nan"]),
        c("calibrate-frames-0", lambda d, p: ["calibrate", str(d / "river.mp4"), "--frames", "0"]),
        c("calibrate-no-board", lambda d, p: ["calibrate", str(d / "river.mp4"), "--out", str(d / "cal.toml")]),
        c("calibrate-video-fifo", lambda d, p: os.mkfifo(d / "ff.mp4") or ["calibrate", str(d / "ff.mp4")]),
        c("preview-out-dir", lambda d, p: ["preview", str(p), "--out", str(d)]),
        c("preview-out-proc", lambda d, p: ["preview", str(p), "--out", "/proc/x.png"]),
        c("report-list-json", report_json(b"[1,2]")),
        c("report-nan-json", report_json(b'{"discharge_m3s": NaN, "files": {}}'), refuse=False),  # an old result
        c("report-binary-json", report_json(bytes(range(256)))),
        c("report-files-not-dict", report_json(b'{"files": [1]}')),
        c("report-missing", lambda d, p: ["report", str(d / "nope"), "--db", str(d / "h.db")]),
        c("history-export-dir", lambda d, p: ["history", "export", str(d), "--db", str(d / "h.db")]),
        c("init-afile", lambda d, p: (d / "afile").write_text("x") and ["init", str(d / "afile")]),
        c("init-proc", lambda d, p: ["init", "/proc/fieldtool_fuzz"]),
        c("batch-levels-latin1", levels("video;niveau_m\nclip é.mp4;1,5\n".encode("latin-1"))),
        c("batch-levels-no-delimiter", levels(b"videowaterlevel\nabc\n")),
        c("batch-levels-binary", levels(bytes(range(256)))),
        c("batch-same-out", batch_same_out),
        c("batch-list-missing", lambda d, p: ["batch", "--list", str(d / "nope.txt"), "--no-history"]),
    ]


# ---------------------------------------------------------------------------------------------
# running and checking


def snapshot(folder: Path) -> dict[str, bytes] | None:
    if not folder.is_dir():
        return None
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def strict_load(data: bytes) -> Any:
    def bad(c):
        raise ValueError(f"non-JSON constant {c}")

    return json.loads(data, parse_constant=bad)


def check_output(out: Path, before: dict[str, bytes] | None, rc: int) -> tuple[bool, bool]:
    """(partial, non_json) of an output folder after a case."""
    if not out.exists():
        return False, False
    rj = out / "result.json"
    if not rj.is_file():
        # no result: only allowed if the folder holds no result files at all (the PIV cache may stay)
        leftovers = [p.name for p in out.iterdir() if p.name not in ("piv_cache.npz",)]
        return bool(leftovers), False
    try:
        summary = strict_load(rj.read_bytes())
    except ValueError:
        return False, True
    if not isinstance(summary, dict):
        return True, False
    files = summary.get("files") or {}
    missing = [n for n in files.values() if isinstance(n, str) and not (out / n).exists()]
    if missing:
        return True, False
    if rc != 0 and rc != 3 and before is not None:
        # a refused run must leave the previous run exactly as it was
        after = snapshot(out)
        changed = [k for k in before if k != "piv_cache.npz" and after.get(k) != before[k]]
        return bool(changed), False
    return False, False


def judge(
    case: Case,
    rc: int,
    stderr: str,
    proj: Path,
    proj_bytes: bytes | None,
    out: Path,
    before: dict[str, bytes] | None,
    hang: bool = False,
) -> Outcome:
    o = Outcome(case, rc, stderr, hang=hang)
    o.traceback = "Traceback" in stderr
    errs = [
        ln
        for ln in stderr.splitlines()
        if ln.strip()
        and not ln.startswith("fieldtool: warning:")
        and not ln.startswith("  ")
        and not ln.startswith("\r")
    ]
    errs = [ln for ln in errs if "\r" not in ln or "fieldtool:" in ln]
    o.multi_line = rc == 2 and len(errs) != 1
    if rc == 2 and errs and not errs[-1].startswith("fieldtool: error:"):
        o.multi_line = True
    o.wrong_code = rc not in ((2,) if case.must_refuse else (0, 2, 3))
    if proj_bytes is not None and not case.command:
        try:
            o.damaged_project = proj.read_bytes() != proj_bytes
        except OSError:
            o.damaged_project = True
    o.partial_output, o.non_json = check_output(out, before, rc)
    return o


def run_in_process(argv: list[str]) -> tuple[int, str]:
    """``fieldtool.cli.main.main(argv)`` with stdout/stderr captured: (exit code, stderr)."""
    from fieldtool.cli import main as cli

    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = cli.main(argv)
        except SystemExit as e:
            rc = int(e.code or 0)
        except BaseException:  # noqa: BLE001 - the guard failed: count it as a traceback
            import traceback

            err.write("Traceback (escaped the CLI guard)\n" + traceback.format_exc())
            rc = 99
    return rc, err.getvalue()


def run_subprocess(argv: list[str], cwd: Path, timeout: float = 240.0) -> tuple[int, str, bool]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), FIELDTOOL_DB=str(cwd / "h.db"))
    try:
        p = subprocess.run(
            [sys.executable, "-m", "fieldtool.cli.main", *argv],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
        )
        return p.returncode, p.stderr, False
    except subprocess.TimeoutExpired as e:
        return 124, (e.stderr or b"").decode() if isinstance(e.stderr, bytes) else (e.stderr or ""), True


class Runner:
    """Runs cases against a prepared scene folder (project.toml, river.mp4, cross_section.csv)
    whose output folder ``seed_out`` already holds a complete run (so PIV is reused where the
    case leaves its inputs alone, and a refused run can be checked to leave it intact)."""

    def __init__(self, scene: Path, seed_out: Path, work: Path):
        self.scene, self.seed_out, self.work = scene, seed_out, work
        self.base = tomllib.loads((scene / "project.toml").read_text(encoding="utf-8"))
        self.n = 0

    def _folder(self, case: Case) -> Path:
        self.n += 1
        d = self.work / f"{self.n:04d}"
        # hard links: fieldtool replaces files (atomic writes, swapped folders), never edits them in place
        shutil.copytree(self.scene, d, ignore=shutil.ignore_patterns("out", "*.rrd"), copy_function=os.link)
        for name in ("project.toml", "cross_section.csv"):  # the cases edit these in place: own copies
            data = (d / name).read_bytes()
            (d / name).unlink()
            (d / name).write_bytes(data)
        return d

    def run(self, case: Case) -> Outcome:
        d = self._folder(case)
        proj = d / "project.toml"
        out = d / "out"
        shutil.copytree(self.seed_out, out, copy_function=os.link)
        if case.setup is None:
            data = with_value(self.base, case.key, case.value) if case.key else self.base
            proj.write_text(to_toml(data), encoding="utf-8")
            proj_bytes = proj.read_bytes()
            before = snapshot(out)
            rc, stderr = run_in_process(["run", str(proj), "--out", str(out), "--quiet"])
            o = judge(case, rc, stderr, proj, proj_bytes, out, before)
        else:
            argv = case.setup(d, proj)
            proj_bytes = proj.read_bytes() if proj.is_file() else None
            before = snapshot(out)
            rc, stderr, hang = run_subprocess(argv, d)
            o = judge(case, rc, stderr, proj, proj_bytes, out, before, hang=hang)
        if o.ok:
            shutil.rmtree(d, ignore_errors=True)
        return o


def totals(outcomes: list[Outcome]) -> dict[str, Any]:
    codes: dict[int, int] = {}
    for o in outcomes:
        codes[o.rc] = codes.get(o.rc, 0) + 1
    return {
        "cases": len(outcomes),
        "exit_codes": dict(sorted(codes.items())),
        "tracebacks": sum(o.traceback for o in outcomes),
        "multi_line_errors": sum(o.multi_line for o in outcomes),
        "wrong_exit_codes": sum(o.wrong_code for o in outcomes),
        "non_json_results": sum(o.non_json for o in outcomes),
        "damaged_projects": sum(o.damaged_project for o in outcomes),
        "partial_output_folders": sum(o.partial_output for o in outcomes),
        "hangs": sum(o.hang for o in outcomes),
    }
