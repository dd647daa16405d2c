"""The long version of tests/tui/test_two_editors.py: the TUI (Pilot) and a viewer in another process edit
the GCPs of one project file, N interleaved edits (default 1000; the test runs 50), seeded.

    nice -n 10 .venv/bin/python benchmarks/two_editors.py [--edits 1000]

Prints the number of edits and whether any was lost (exit status 0 when none was) and how long the TUI
took, at worst, to show the viewer's pick.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--edits", type=int, default=1000)
    args = ap.parse_args()
    env = dict(os.environ, FIELDTOOL_TWO_EDITORS_EDITS=str(args.edits),
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    test = ROOT / "tests" / "tui" / "test_two_editors.py"
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", str(test), "-k", "fifty"]
    out = subprocess.run(cmd, env=env, cwd=ROOT, check=False)
    print(f"{args.edits} interleaved edits of the TUI and a viewer process: "
          f"{'none lost' if out.returncode == 0 else 'EDITS LOST or a check failed (see above)'}")
    return out.returncode


if __name__ == "__main__":
    raise SystemExit(main())
