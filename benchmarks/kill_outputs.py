"""kill -9 at N random moments of a run over an existing output folder (issue 25; the test suite runs 5).

After each kill the output folder must be the old run or the new one, byte for byte (tests/outputs_harness.py
``verdict``: files every run writes afresh, result.json and mean_field.nc, must still be the new run's and agree
with its mean_field.npz), and after the next complete run no temporary folder or lock may be left beside it.
Prints one line per kill and a summary; exits 1 when any kill left a mixed or missing folder.

    .venv/bin/python benchmarks/kill_outputs.py              # 30 kills, seed 25
    .venv/bin/python benchmarks/kill_outputs.py --n 100 --seed 7
"""

from __future__ import annotations

import argparse
import random
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import tomli_w

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from outputs_harness import kill_once, snapshot, temp_leftovers, time_phases, verdict

HARNESS = ROOT / "tests" / "outputs_harness.py"


def child(argv, frame_delay=0.01, write_delay=0.05):
    return subprocess.Popen([sys.executable, str(HARNESS), str(frame_delay), str(write_delay), *map(str, argv)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def run(argv) -> None:
    p = child(argv, 0, 0)
    _, err = p.communicate()
    if p.returncode != 0:
        raise SystemExit(f"run failed ({p.returncode}): {err.decode()[-500:]}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30, help="kills (default 30)")
    ap.add_argument("--seed", type=int, default=25)
    args = ap.parse_args()
    from fieldtool.synthetic import presets, render_scene

    work = Path(tempfile.mkdtemp(prefix="kill_outputs_"))
    try:
        truth = render_scene(presets.get("oblique", duration_s=1.2), work)
        data = tomllib.loads(truth.project_path.read_text())
        data["section"]["n_sub"] = 7
        data["piv"]["window_px"] = 24
        new_proj = work / "new.toml"
        new_proj.write_text(tomli_w.dumps(data))
        old_proj, out = truth.project_path, work / "out"
        run(["run", old_proj, "--out", out, "--quiet"])
        old = snapshot(out)
        shutil.copytree(out, work / "ref")
        run(["run", new_proj, "--out", work / "ref", "--quiet"])
        new = snapshot(work / "ref")
        shutil.rmtree(work / "ref")
        shutil.copytree(out, work / "timed")
        span, write_span = time_phases(lambda: child(["run", new_proj, "--out", work / "timed", "--quiet"]), work)
        shutil.rmtree(work / "timed", ignore_errors=True)
        print(f"a slowed run takes {span:.1f} s, its writing {write_span:.1f} s; {args.n} kills (seed {args.seed}), "
              "half over the whole run, half over the writing")
        rng = random.Random(args.seed)
        counts = {"old": 0, "new": 0, "bad": 0}
        for i in range(args.n):
            if snapshot(out) != old:
                shutil.rmtree(out)
                run(["run", old_proj, "--out", out, "--quiet"])
                old = snapshot(out)
            when = kill_once(lambda: child(["run", new_proj, "--out", out, "--quiet"]), work, rng, span, write_span)
            v = verdict(snapshot(out), old, new)
            counts[v if v in ("old", "new") else "bad"] += 1
            print(f"{i + 1:3d}  kill {when}  ->  {v}  (left beside it: {len(temp_leftovers(work))})", flush=True)
        run(["run", new_proj, "--out", out, "--quiet"])
        left = temp_leftovers(work)
        print(f"old {counts['old']}, new {counts['new']}, mixed or missing {counts['bad']}; "
              f"left after the next run: {left or 'nothing'}")
        return 1 if counts["bad"] or left else 0
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
