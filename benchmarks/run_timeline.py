"""One ``fieldtool run``, as a timeline: when each stage starts and ends, and how many cores the run uses meanwhile.

    PYTHONPATH=. .venv/bin/python benchmarks/run_timeline.py /tmp/ft_time_to_q/720p_8s/noroi.toml

The project (any; time_to_q.py's clips are rendered under /tmp/ft_time_to_q) runs once, in a process of its own
and a session of its own, with the defaults, into a temporary folder removed afterwards (``--tree``: another source
tree's code, run from its own folder). Printed:

* the stage marks, from wrappers around the run's stages in that process (when each starts, s after this script
  started the process, and its own s): the imports, STIV's lines, the clip check, the first look, the pass
  (frames and PIV), STIV's analysis, the Monte Carlo and the verdict, the writing (which waits for the figures);
* every 0.1 s, the cores used by the run's threads (by role: the main thread, the frame threads that decode and
  standardise, the engine's workers, the rest) and by the figure processes, from ``/proc`` (user + system
  ticks of each thread of the session), with the marks that fell in each interval.

A row whose total is well under the host's cores while nothing else runs shows where the run leaves a core idle.
The wrappers add a few microseconds a call; the sampling costs about 1 % of a core. One run, no medians: read it
for the shape of the run, not for a timing (use tree_ab.py or cpu_budget.py for those).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import time_to_q as ttq  # noqa: E402

# the run, in-process: marks around its stages and the name of each thread (by its kernel id), printed at exit
WRAPPER = r"""
import atexit, functools, json, os, sys, threading, time
t0 = float(os.environ["RUN_TIMELINE_T0"])  # the parent's clock (time.time) when it started this process
marks, names = [], {}
_set = threading.Thread._set_native_id
def _named(self):
    _set(self)
    names[self.native_id] = self.name
threading.Thread._set_native_id = _named
def wrap(mod, name, label):
    f = getattr(mod, name)
    @functools.wraps(f)
    def g(*a, **k):
        t = time.time()
        try:
            return f(*a, **k)
        finally:
            marks.append((label, t - t0, time.time() - t))
    setattr(mod, name, g)
from fieldtool.cli import main as cli
marks.append(("interpreter and the CLI's imports", 0.0, time.time() - t0))
_load = cli.load_measure
def load_measure():  # cmd_run forks the figure process, then imports the run: the wrappers go on after that
    t = time.time()
    measure = _load()
    marks.append(("the run's imports", t - t0, time.time() - t))
    from fieldtool.processing import planning
    from fieldtool.run import clip_check, discharge, outputs, quality, stiv_stage, velocimetry
    for mod, name, label in ((stiv_stage, "start", "STIV lines"), (clip_check, "check", "clip check"),
                             (planning, "first_look", "first look"),
                             (velocimetry, "measure_velocity", "frames and PIV"),
                             (discharge, "add_stiv", "STIV analysis"), (quality, "judge", "Monte Carlo, verdict"),
                             (outputs, "write_outputs", "writing (figures waited)")):
        wrap(mod, name, label)
    return measure
cli.load_measure = load_measure
names[threading.main_thread().native_id] = "main"
atexit.register(lambda: print("TIMELINE " + json.dumps({"marks": marks, "names": names}), file=sys.stderr))
sys.argv = ["fieldtool"] + sys.argv[1:]
cli.main()
"""

TICK = os.sysconf("SC_CLK_TCK")


def session_threads(sid: int) -> dict[tuple[int, int], float]:
    """CPU s so far of every thread of every process in session ``sid``: {(pid, tid): s}."""
    out = {}
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            stat = Path(f"/proc/{p}/stat").read_text()
            if int(stat.rsplit(")", 1)[1].split()[3]) != sid:
                continue
            for t in os.listdir(f"/proc/{p}/task"):
                f = Path(f"/proc/{p}/task/{t}/stat").read_text().rsplit(")", 1)[1].split()
                out[(int(p), int(t))] = (int(f[11]) + int(f[12])) / TICK
        except (OSError, IndexError, ValueError):  # a thread or process that ended meanwhile
            continue
    return out


def role(pid: int, tid: int, run_pid: int, names: dict[int, str]) -> str:
    if pid != run_pid:
        return "figures"
    name = names.get(tid, "")
    if name == "main":
        return "main"
    if "_fill" in name:
        return "frames"
    if name.startswith("piv"):
        return "engine"
    return "other"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("--every", type=float, default=0.1, help="s between samples")
    ap.add_argument("--tree", type=Path, default=HERE.parent, help="the source tree run (this repository's)")
    args = ap.parse_args()
    tree = args.tree.resolve()
    if not (tree / "fieldtool").is_dir():
        ap.error(f"--tree {args.tree}: no fieldtool package there; give a checkout of this repository")
    t0 = time.time()
    # run from the tree's folder: a -c launcher imports fieldtool from the working directory before PYTHONPATH
    env = dict(os.environ, PYTHONPATH=str(tree), RUN_TIMELINE_T0=repr(t0))
    with tempfile.TemporaryDirectory(prefix="run_timeline_") as tmp:
        cmd = [sys.executable, "-c", WRAPPER, "run", str(args.project.resolve()), "--out", str(Path(tmp) / "out")]
        p = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd=tree, start_new_session=True
        )
        err: list[bytes] = []
        reader = threading.Thread(target=lambda: err.extend(p.stderr or []), daemon=True)
        reader.start()
        samples = []
        while p.poll() is None:
            samples.append((time.time() - t0, session_threads(p.pid)))
            time.sleep(args.every)
        wall = time.time() - t0
        reader.join(5)
    text = b"".join(err).decode(errors="replace")
    line = next((x for x in text.splitlines() if x.startswith("TIMELINE ")), None)
    if line is None or p.returncode not in (0, 3):  # 3: a measurement graded unusable, its stages all ran
        said = "\n".join(x for x in text.splitlines() if not x.startswith("TIMELINE "))
        print(f"the run exited {p.returncode}: {said[-500:]}", file=sys.stderr)
        sys.exit(p.returncode or 1)  # its own code (2: bad input); 1 when it left no timeline at exit 0
    info = json.loads(line[len("TIMELINE ") :])
    names = {int(k): v for k, v in info["names"].items()}
    print(
        f"{args.project}: {wall:.2f} s wall, exit {p.returncode}, {ttq.cores()} cores, load average "
        f"{os.getloadavg()[0]:.2f}\n\n| stage | starts s | takes s |\n|---|---|---|"
    )
    for label, start, took in sorted(info["marks"], key=lambda m: m[1]):
        print(f"| {label} | {start:.2f} | {took:.2f} |")
    roles = ["main", "frames", "engine", "other", "figures"]
    print("\n  t s  " + " ".join(f"{r:>7s}" for r in roles) + "    all | marks")
    prev_t, prev = 0.0, {}
    totals = dict.fromkeys(roles, 0.0)
    for t, snap in samples:
        used = dict.fromkeys(roles, 0.0)
        for key, s in snap.items():
            used[role(*key, p.pid, names)] += s - prev.get(key, 0.0)
        for r in roles:
            totals[r] += used[r]
        dt = max(t - prev_t, 1e-9)
        began = [m[0] for m in info["marks"] if prev_t < m[1] <= t]
        print(
            f"{t:5.2f}  "
            + " ".join(f"{used[r] / dt:7.2f}" for r in roles)
            + f" {sum(used.values()) / dt:6.2f} | {', '.join(began)}"
        )
        prev_t, prev = t, {**prev, **snap}
    print(
        "  CPU s " + " ".join(f"{totals[r]:7.2f}" for r in roles) + f" {sum(totals.values()):6.2f}"
        " (threads and processes that ended between two samples lose their last interval)"
    )
    # each thread of the run's process by its Python name (its kernel id for a thread Python did not start: the
    # process has ended, so /proc no longer names it), the CPU s it used and the span it was sampled in: the
    # frames role is several threads of a pipeline
    first: dict[tuple[int, int], float] = {}
    last: dict[tuple[int, int], float] = {}
    for t, snap in samples:
        for key in snap:
            first.setdefault(key, t)
            last[key] = t
    print("\n| thread | role | CPU s | from s | to s |\n|---|---|---|---|---|")
    for key in sorted(prev, key=lambda k: -prev[k]):
        if key[0] != p.pid or prev[key] < 0.05:
            continue
        print(
            f"| {names.get(key[1], f'thread {key[1]}')} | {role(*key, p.pid, names)} | {prev[key]:.2f} | "
            f"{first[key]:.2f} | {last[key]:.2f} |"
        )


if __name__ == "__main__":
    main()
