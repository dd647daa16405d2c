"""Every fuzz case (tests/fuzz_cases.py): each key of the project file x bad values, broken files
and broken inputs to the other subcommands, against a rendered 1.2 s oblique scene.

    nice -n 10 .venv/bin/python benchmarks/fuzz_all.py [--work /tmp/fuzz] [--only SUBSTRING]

Prints the totals (cases, exit codes, tracebacks, multi-line errors, wrong exit codes, non-JSON
results, damaged projects, partial output folders, hangs) and every failing case. Key cases run in
this process (fieldtool.cli.main.main), file and command cases as subprocesses (a hang is a timeout).
Exit status 0 when every case passes.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

import fuzz_cases as F  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one, removed)")
    ap.add_argument("--only", default="", help="run only cases whose id contains this")
    ap.add_argument("--json", default=None, help="also write the totals and failures here")
    args = ap.parse_args()
    from fieldtool.cli.main import main as cli_main
    from fieldtool.project.model import load_project
    from fieldtool.synthetic import presets, render_scene

    work = Path(args.work or tempfile.mkdtemp(prefix="fieldtool_fuzz_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = work / "scene"
    if not (scene / "project.toml").is_file():
        render_scene(presets.get("oblique", duration_s=1.2), scene)
    seed = work / "seed_out"
    if not (seed / "result.json").is_file():
        assert cli_main(["run", str(scene / "project.toml"), "--out", str(seed), "--quiet"]) == 0
    shutil.rmtree(work / "cases", ignore_errors=True)
    runner = F.Runner(scene, seed, work / "cases")
    gcp = load_project(scene / "project.toml").ortho.gcp_px
    cases = F.key_cases(full=True) + F.geometry_cases(gcp) + F.file_cases() + F.command_cases()
    cases = [c for c in cases if args.only in c.id]
    outcomes = []
    for i, c in enumerate(cases):
        o = runner.run(c)
        outcomes.append(o)
        if not o.ok:
            flags = [k for k in ("traceback", "multi_line", "wrong_code", "non_json", "damaged_project",
                                 "partial_output", "hang") if getattr(o, k)]
            print(f"FAIL {c.id}: exit {o.rc} {flags} :: {o.stderr.strip().splitlines()[-1][:200] if o.stderr.strip() else ''}",
                  flush=True)
    tot = F.totals(outcomes)
    tot["key_cases"] = sum(1 for o in outcomes if o.case.setup is None)
    tot["file_cases"] = sum(1 for o in outcomes if o.case.setup is not None and not o.case.command)
    tot["command_cases"] = sum(1 for o in outcomes if o.case.command)
    tot["failing_cases"] = sum(1 for o in outcomes if not o.ok)
    tot["seconds"] = round(time.perf_counter() - t0, 1)
    tot["load_average"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(tot, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps({"totals": tot, "failures": [
            {"id": o.case.id, "rc": o.rc, "stderr": o.stderr[-500:]} for o in outcomes if not o.ok]}, indent=2))
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if tot["failing_cases"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
