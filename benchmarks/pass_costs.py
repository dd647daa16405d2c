"""Where the second PIV pass spends its time in a default run, and how much window shifting could save.

    nice -n 10 .venv/bin/python benchmarks/pass_costs.py [--duration 2] [--scenes oblique,nadir,ripples,glints_section]

Per synthetic scene, run as the generator wrote it (default keys: 2 passes, window 32 / overlap 16, the band
around the section, pairs added until converged):

* ``shift ok``: the share of final-pass windows where the predictor field is nearly uniform, i.e. its largest
  displacement gradient (px/px, over both components and both axes, from the first pass' field) times the
  final window side is under 0.05 / 0.1 / 0.25 px. There an integer window shift would give the deformed
  window's answer; elsewhere the frame has to be deformed (``cv2.remap``). Windows overlap by half, so the
  remap could only be skipped over a region where (nearly) every window qualifies.
* ``remap``, ``fft``, ``piv``, ``run``: seconds of the (second, fresh) end-to-end run spent in ``cv2.remap`` of
  the deformation, in the pocketfft calls, in ``piv.analyze`` (correlation, peaks, validation) and in the
  whole ``run_project`` (cProfile, main thread; decoding runs in the reader thread and shows as waiting inside
  ``analyze``).

Prints the load average; on a shared machine the seconds are noisy, the shares less so.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import tempfile
from pathlib import Path

import numpy as np

from fieldtool import pipeline
from fieldtool.pipeline import run_project
from fieldtool.processing import piv
from fieldtool.project import load_project
from fieldtool.synthetic import presets, render_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=2.0, help="clip length (s)")
    ap.add_argument("--scenes", default="oblique,nadir,ripples,glints_section")
    args = ap.parse_args()
    pipeline.write_outputs = lambda *a, **k: None  # the numbers only

    grads: list[np.ndarray] = []
    deform = piv._Engine._deform

    def recording(self, k, img, du, dv):
        prev, lv = self.levels[k - 1], self.levels[k]
        g = np.zeros(np.shape(du))
        for f in (du, dv):
            gy, gx = np.gradient(np.asarray(f, float))
            g = np.maximum(g, np.maximum(abs(gx), abs(gy)) / prev.step)
        grads.append(g.ravel() * lv.w)  # px of predictor change across one final window
        return deform(self, k, img, du, dv)

    piv._Engine._deform = recording
    print(f"load average {os.getloadavg()[0]:.1f}; clips of {args.duration:g} s")
    print("| scene | pairs deformed | shift ok < 0.05 px | < 0.1 px | < 0.25 px | remap (s) | fft (s) | piv (s) | run (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes.split(","):
            d = Path(tmp) / name
            render_scene(presets.get(name, duration_s=args.duration), d)
            run_project(load_project(d / "project.toml"), d / "warm")  # imports, caches
            grads.clear()
            prof = cProfile.Profile()
            prof.enable()
            run_project(load_project(d / "project.toml"), d / "out")
            prof.disable()
            st = pstats.Stats(prof).stats  # {(file, line, name): (cc, nc, tt, ct, callers)}

            def tot(pred, cum=False):
                return sum(v[3] if cum else v[2] for k, v in st.items() if pred(k))

            remap = tot(lambda k: k[2] == "<remap>")
            fft = tot(lambda k: "pypocketfft" in k[2])
            an = tot(lambda k: k[0].endswith("processing/piv.py") and k[2] == "analyze", cum=True)
            run = tot(lambda k: k[2] == "run_project", cum=True)
            a = np.concatenate(grads) if grads else np.zeros(0)
            share = [f"{100 * (a < t).mean():.0f} %" if a.size else "-" for t in (0.05, 0.1, 0.25)]
            print(f"| {name} | {len(grads)} | {' | '.join(share)} | {remap:.2f} | {fft:.2f} | {an:.2f} | {run:.2f} |",
                  flush=True)


if __name__ == "__main__":
    main()
