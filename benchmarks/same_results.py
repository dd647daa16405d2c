"""Same results: run ``fieldtool run PROJECT --out DIR`` on scenes and diff result.json against a baseline.

A refactor that must not change behaviour is checked with it: every key of result.json must be equal,
except the wall-clock ones (``timings_s`` and any key named in ``IGNORED``). Each scene is run into a fresh
folder (a ``piv_cache.npz`` left in the output folder would be reused and hide a change in the PIV).

    python benchmarks/same_results.py --baseline /tmp/baseline oblique nadir ...

runs the fieldtool that PYTHONPATH (or the environment) gives; reads ``BASELINE/<scene>/scene/project.toml`` and ``BASELINE/<scene>/results/result.json``; prints one line
per scene (``same`` or the differing keys, dotted paths, with both values) and exits 1 when any differs.
``--make SCENES_DIR`` writes the baseline instead, with the fieldtool PYTHONPATH gives (a worktree of the commit
before: ``PYTHONPATH=/tmp/before python benchmarks/same_results.py --make /tmp/unseen_scenes --baseline
/tmp/sr_base <scenes>``). ``--tolerance`` (relative, default 0) lets numbers differ by that much (for changes that are meant to move
the results slightly); the differences are still printed, with their relative size.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

IGNORED = {"timings_s", "seconds"}  # wall-clock fields (timings_s, stiv.seconds): they differ between any two runs


def diff(a, b, path: str = "", out: list | None = None) -> list:
    """Dotted paths where ``a`` and ``b`` differ, each as (path, a, b, relative difference or None)."""
    out = [] if out is None else out
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k in IGNORED:
                continue
            p = f"{path}.{k}" if path else k
            if k not in a or k not in b:
                out.append((p, a.get(k, "<absent>"), b.get(k, "<absent>"), None))
            else:
                diff(a[k], b[k], p, out)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            diff(x, y, f"{path}[{i}]", out)
    elif (isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool)
          and not isinstance(b, bool)):
        if a != b:
            rel = abs(a - b) / max(abs(a), abs(b)) if max(abs(a), abs(b)) > 0 else math.inf
            out.append((path, a, b, rel))  # within ``tol`` it is listed but not counted (see main)
    elif a != b:
        out.append((path, a, b, None))
    return out


def run_scene(project: Path, out: Path) -> int:
    cmd = [sys.executable, "-m", "fieldtool.cli", "run", str(project), "--out", str(out)]
    # run from the output folder: ``python -m`` puts the current folder first on sys.path, so the fieldtool
    # measured is the one PYTHONPATH (or the environment) gives, not a checkout the script was started in
    env = os.environ.copy()  # PYTHONPATH absolute: ``PYTHONPATH=.`` would name the output's folder
    if env.get("PYTHONPATH"):
        env["PYTHONPATH"] = os.pathsep.join(str(Path(p).resolve()) for p in env["PYTHONPATH"].split(os.pathsep) if p)
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=out.parent)
    if r.returncode not in (0, 3):
        sys.stderr.write(r.stdout + r.stderr)
    return r.returncode


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--baseline", default="/tmp/baseline", help="folder of <scene>/scene/project.toml and "
                    "<scene>/results/result.json")
    ap.add_argument("--keep", help="write each run to KEEP/<scene> instead of a temporary folder")
    ap.add_argument("--tolerance", type=float, default=0.0, help="relative difference allowed in numbers")
    ap.add_argument("--make", metavar="SCENES_DIR", help="make the baseline instead: BASELINE/<scene>/scene links to "
                    "SCENES_DIR/<scene> and BASELINE/<scene>/results is this fieldtool's run of it")
    args = ap.parse_args(argv)
    base = Path(args.baseline)
    if args.make:
        for scene in args.scenes:
            (base / scene).mkdir(parents=True, exist_ok=True)
            link = base / scene / "scene"
            if not link.exists():
                link.symlink_to(Path(args.make).resolve() / scene)
            shutil.rmtree(base / scene / "results", ignore_errors=True)
            print(f"{scene}: baseline made (exit {run_scene(link / 'project.toml', base / scene / 'results')})")
        return 0
    bad = 0
    for scene in args.scenes:
        want = json.loads((base / scene / "results" / "result.json").read_text())
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(args.keep) / scene if args.keep else Path(tmp) / "out"
            out.parent.mkdir(parents=True, exist_ok=True)
            rc = run_scene(base / scene / "scene" / "project.toml", out)
            got_file = out / "result.json"
            if not got_file.exists():
                print(f"{scene}: no result.json (exit {rc})")
                bad += 1
                continue
            got = json.loads(got_file.read_text())
        d = diff(want, got)
        counted = [x for x in d if x[3] is None or x[3] > args.tolerance]
        if not d:
            print(f"{scene}: same (exit {rc})")
        else:
            print(f"{scene}: {len(counted)} key(s) differ" + (f", {len(d) - len(counted)} within tolerance"
                                                              if len(d) > len(counted) else "") + f" (exit {rc})")
            for p, x, y, rel in d:
                r = f"  rel {rel:.2e}" if rel is not None else ""
                print(f"    {p}: {json.dumps(x)[:80]} -> {json.dumps(y)[:80]}{r}")
        bad += bool(counted)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
