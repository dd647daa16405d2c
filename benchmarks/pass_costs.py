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

``--masked-speed``: instead, the engine alone (``piv.analyze``, 2 passes, 32/16, 8 pairs of 1280 x 720 synthetic
particle frames) with 0 / 30 / 50 % of the frame masked (a bank), the final pass skipping the masked nodes or not
(``piv_engine._SKIP_MASKED``), alternating runs, medians; the 0 % row runs the same code twice (the noise floor).

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

from fieldtool.run import outputs
from fieldtool.run.pipeline import run_project
from fieldtool.processing import piv, piv_engine
from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=2.0, help="clip length (s)")
    ap.add_argument("--scenes", default="oblique,nadir,ripples,glints_section")
    ap.add_argument("--masked-speed", action="store_true", help="time the skipping of masked nodes instead")
    ap.add_argument("--runs", type=int, default=7, help="alternating runs of --masked-speed")
    args = ap.parse_args()
    if args.masked_speed:
        masked_speed(args.runs)
        return
    outputs.write_outputs = lambda *a, **k: None  # the numbers only

    grads: list[np.ndarray] = []
    deform = piv_engine._Engine._deform

    def recording(self, k, img, du, dv):
        prev, lv = self.levels[k - 1], self.levels[k]
        g = np.zeros(np.shape(du))
        for f in (du, dv):
            gy, gx = np.gradient(np.asarray(f, float))
            g = np.maximum(g, np.maximum(abs(gx), abs(gy)) / prev.step)
        grads.append(g.ravel() * lv.w)  # px of predictor change across one final window
        return deform(self, k, img, du, dv)

    piv_engine._Engine._deform = recording
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


def masked_speed(runs: int) -> None:
    import sys
    import time

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "processing"))
    from test_piv import particle_clip  # the test suite's particle renderer

    h, w, pairs = 720, 1280, 8
    frames = particle_clip(lambda x, y: (2.0 + 0 * x, 1.0 + 0 * y), h=h, w=w, n_frames=pairs + 1, seed=1)
    params = piv.PivParams(window_px=32, overlap_px=16, passes=2)
    print(f"{pairs} pairs of {w} x {h} px, 2 passes, 32/16, {runs} alternating runs")
    print("| masked | skip off (pairs/s) | skip on (pairs/s) | ratio of medians | median of ratios | load |")
    print("|---|---|---|---|---|---|")
    for frac in (0.0, 0.3, 0.5):
        mask = np.zeros((h, w), bool)
        mask[:, : int(frac * w)] = True
        t: dict[bool, list[float]] = {False: [], True: []}
        for _ in range(runs):
            for skip in (False, True):
                piv_engine._SKIP_MASKED = skip
                t0 = time.perf_counter()
                piv.analyze(frames, params, mask=mask if frac else None)
                t[skip].append(time.perf_counter() - t0)
        off, on = np.median(t[False]), np.median(t[True])
        ratio = np.median(np.array(t[False]) / np.array(t[True]))
        print(f"| {frac:.0%} | {pairs / off:.2f} | {pairs / on:.2f} | {off / on:.2f} | {ratio:.2f} | "
              f"{os.getloadavg()[0]:.1f} |", flush=True)
    piv_engine._SKIP_MASKED = True


if __name__ == "__main__":
    main()
