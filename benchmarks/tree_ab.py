"""Two source trees of fieldtool, one project: alternating end-to-end runs, medians of wall s, CPU s and peak MiB.

    git worktree add /tmp/before <commit>
    .venv/bin/python benchmarks/tree_ab.py --before /tmp/before --after . --runs 5 PROJECT [PROJECT ...]
    .venv/bin/python benchmarks/tree_ab.py --before . --before-env OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN=10000 PROJECT

Each run is ``python -m fieldtool.cli.main run PROJECT --out <fresh folder>`` in a process of its own with
``PYTHONPATH=<tree>`` (interpreter start and imports included), the trees alternating, after both were
byte-compiled (as pip does for an installed package: a tree without bytecode would compile every module on every
run). The CPU seconds are the process' and its children's (user + system); the peak is the largest resident set
of the process or a child. The load average is printed before and after: only the ratio within one call carries.
The discharge of each tree's last run is printed too (the same when a change keeps the numbers).
``--before-env KEY=VALUE`` (repeatable) sets a variable for the "before" runs only: one tree against itself with
a setting of the environment changed (stop 37: fieldtool/__init__.py's OpenCV pool defaults,
``--before-env OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER=2000 --before-env OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN=10000``,
OpenCV's own defaults).
``--before-set SECTION.KEY=VALUE`` (repeatable, VALUE in TOML) runs the "before" tree on a copy of each project with
those keys set, written beside it as ``<name>_before.toml``: a tree whose default changed, against the one before
with the old default said (stop 52: ``--before-set 'section.velocity_source="piv"'``, a key value the tree before
did not know).
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tomlkit


def run(tree: Path, project: Path, extra_env: dict[str, str] | None = None) -> dict:
    out = Path(tempfile.mkdtemp(prefix="tree_ab_"))
    shutil.rmtree(out)
    env = dict(os.environ, PYTHONPATH=str(tree), **(extra_env or {}))
    t0 = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, "-m", "fieldtool.cli.main", "run", str(project), "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
        cwd=tree,
    )
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    err = p.stderr.read().decode(errors="replace") if p.stderr else ""
    rc = os.waitstatus_to_exitcode(status)
    res = json.loads((out / "result.json").read_text()) if (out / "result.json").exists() else {}
    shutil.rmtree(out, ignore_errors=True)
    if rc not in (0, 3):
        raise RuntimeError(f"{tree}: exit {rc}: {err[-500:]}")
    stiv_s = (res.get("stiv") or {}).get("seconds")  # STIV's own timer: line sampling and analysis
    return {
        "s": wall,
        "cpu": ru.ru_utime + ru.ru_stime,
        "mib": ru.ru_maxrss / 1024,
        "q": res.get("discharge_m3s"),
        "stiv_s": stiv_s,
    }


def with_keys(project: Path, sets: list[str]) -> Path:
    """``project`` with the keys of ``sets`` ("section.key=<TOML value>") set, as ``<name>_before.toml`` beside it."""
    doc = tomlkit.parse(project.read_text())
    for kv in sets:
        path, value = kv.split("=", 1)
        *tables, key = path.split(".")
        node = doc
        for t in tables:
            node = node.setdefault(t, tomlkit.table())
        node[key] = tomlkit.parse(f"v = {value}")["v"]
    out = project.with_name(f"{project.stem}_before.toml")
    out.write_text(tomlkit.dumps(doc))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("projects", nargs="+", type=Path)
    ap.add_argument("--before", type=Path, required=True, help="the tree before (a git worktree)")
    ap.add_argument("--after", type=Path, default=Path("."), help="the tree after (default: this one)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--before-env", action="append", default=[], metavar="KEY=VALUE", help="for the before runs")
    ap.add_argument("--before-set", action="append", default=[], metavar="KEY=VALUE", help="project keys, before")
    a = ap.parse_args()
    envs = {"before": dict(kv.split("=", 1) for kv in a.before_env), "after": {}}
    trees = {"before": a.before.resolve(), "after": a.after.resolve()}
    for t in trees.values():
        compileall.compile_dir(str(t / "fieldtool"), quiet=1)
    for project in a.projects:
        load0 = os.getloadavg()[0]
        got: dict[str, list] = {k: [] for k in trees}
        projects = {"before": project.resolve(), "after": project.resolve()}
        if a.before_set:
            projects["before"] = with_keys(project.resolve(), a.before_set)
        for _ in range(a.runs):
            for name, tree in trees.items():
                got[name].append(run(tree, projects[name], envs[name]))
        print(
            f"\n== {project} ({a.runs} alternating runs; load average {load0:.2f} before, "
            f"{os.getloadavg()[0]:.2f} after)"
        )
        med = {}
        for name, rs in got.items():
            med[name] = float(np.median([r["s"] for r in rs]))
            walls = " ".join(f"{r['s']:.2f}" for r in rs)
            cpu = float(np.median([r["cpu"] for r in rs]))
            peak = max(r["mib"] for r in rs)
            q = rs[-1]["q"]
            st = [r["stiv_s"] for r in rs if r["stiv_s"] is not None]
            stiv_s = f"  STIV {float(np.median(st)):.3f} s" if st else ""
            print(f"{name:7s} wall {med[name]:6.2f} s ({walls})  CPU {cpu:6.2f} s  peak {peak:5.0f} MiB{stiv_s}  Q {q}")
        note = f" (before with {' '.join(a.before_env + a.before_set)})" if a.before_env or a.before_set else ""
        print(f"after / before: {med['after'] / med['before']:.3f} in wall time{note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
