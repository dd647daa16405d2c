"""fieldtool's PIV engine against OpenPIV on identical image pairs: throughput, peak memory, accuracy.

Run:  .venv/bin/python benchmarks/piv_vs_openpiv.py [--runs 5] [--pairs 4] [--ensemble-pairs 150] [--long]

Speed: 1920 x 1080 synthetic particle frames, window 32, overlap 16. Each run times, in turn,
  OpenPIV pyprocess.extended_search_area_piv (per pair, on frame arrays),
  fieldtool single pass (averaging = mean),
  fieldtool ensemble (averaging = ensemble) on a clip of ``--ensemble-pairs`` pairs (default 150: 5 s at 30 fps;
    the frames cycle through the same pool), because ensemble mode computes per-pair vectors only on a sample
    of 30 to 59 evenly spaced pairs and its cost per pair depends on the clip length; once with the clip's
    length known (``len(frames)``, as a video reader knows it) and once as a bare iterator (length unknown:
    the sample stride grows by doubling, so more pairs get vectors),
  OpenPIV windef.simple_multipass 64 -> 32 (its defaults otherwise),
  fieldtool passes = 2 (64 -> 32),
and the medians of pairs/s over the runs are printed with their ratios. fieldtool is timed through the public
``analyze`` on a stream of frames (one frame at a time; validation and averaging included); OpenPIV through
its own calls only
(OpenPIV has no ensemble mode: its per-pair rate does not depend on the clip length).
Peak memory: tracemalloc peak of one call per engine (Python and NumPy allocations). ``--long`` also streams a
15 s, 30 fps 1080p clip (450 frames, generated on the fly) through ``analyze`` and reports its peak.

Accuracy: 512 x 384 frames (3 frames = 2 pairs) with known displacement: uniform sub-pixel shift, linear shear,
Rankine vortex, with particle density and diameter varied. Bias (mean error of u and v) and RMS of the vector
error in px, over the nodes each engine reports valid (the same fieldtool validation is applied to both engines'
vectors; replaced nodes excluded), and the share of valid nodes.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import resource
import sys
import time
import tracemalloc

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import piv_synth as syn  # noqa: E402
from openpiv import pyprocess, windef  # noqa: E402
from openpiv.settings import PIVSettings  # noqa: E402

from fieldtool.processing.piv import PivParams, analyze  # noqa: E402

H, W = 1080, 1920


def openpiv_esa(frames):
    for (_, a), (_, b) in zip(frames[:-1], frames[1:]):
        pyprocess.extended_search_area_piv(a, b, window_size=32, overlap=16, search_area_size=32,
                                           sig2noise_method="peak2peak", subpixel_method="gaussian")


def openpiv_windef(frames):
    st = PIVSettings()
    st.windowsizes, st.overlap, st.num_iterations = (64, 32), (32, 16), 2
    with contextlib.redirect_stdout(io.StringIO()):
        for (_, a), (_, b) in zip(frames[:-1], frames[1:]):
            windef.simple_multipass(a, b, st)


class Stream:
    """Frames handed over one at a time, with a known length (``len``) as a video reader knows its frame count."""

    def __init__(self, frames):
        self.frames = frames

    def __len__(self):
        return len(self.frames)

    def __iter__(self):
        yield from self.frames


def ours(averaging, passes=1, sized=True):
    def run(frames):
        src = Stream(frames) if sized else iter(frames)
        analyze(src, PivParams(window_px=32, overlap_px=16, passes=passes, averaging=averaging))

    return run


ENGINES = [  # name, call, clip ("pairs": --pairs pairs; "ensemble": --ensemble-pairs pairs)
    ("OpenPIV extended_search_area_piv", openpiv_esa, "pairs"),
    ("fieldtool single pass (mean)", ours("mean"), "pairs"),
    ("fieldtool ensemble", ours("ensemble"), "ensemble"),
    ("fieldtool ensemble, unknown length", ours("ensemble", sized=False), "ensemble"),
    ("OpenPIV windef 64->32", openpiv_windef, "pairs"),
    ("fieldtool 2 passes 64->32 (mean)", ours("mean", passes=2), "pairs"),
]


def speed(runs: int, n_pairs: int, ens_pairs: int):
    frames = syn.clip(syn.rankine(W / 2, H / 2, rc=200, vmax=5.0), H, W, n_frames=n_pairs + 1, density=0.03)
    clips = {"pairs": frames,  # the same arrays again, new timestamps (30 fps): no extra memory
             "ensemble": [(k / 30.0, frames[k % len(frames)][1]) for k in range(ens_pairs + 1)]}
    times = {name: [] for name, _, _ in ENGINES}
    for _ in range(runs):
        for name, fn, clip in ENGINES:  # alternating: every run times each engine once, in turn
            t0 = time.perf_counter()
            fn(clips[clip])
            times[name].append((len(clips[clip]) - 1) / (time.perf_counter() - t0))
    mem = {}
    for name, fn, _ in ENGINES:
        tracemalloc.start()
        fn(frames[:3])
        mem[name] = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    med = {k: float(np.median(v)) for k, v in times.items()}
    ref = {"fieldtool single pass (mean)": "OpenPIV extended_search_area_piv",
           "fieldtool ensemble": "OpenPIV extended_search_area_piv",
           "fieldtool ensemble, unknown length": "OpenPIV extended_search_area_piv",
           "fieldtool 2 passes 64->32 (mean)": "OpenPIV windef 64->32"}
    print(f"\nSpeed: {W}x{H}, window 32, overlap 16, {n_pairs} pairs per call ({ens_pairs} for the ensemble), "
          f"{runs} alternating runs, {os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.2f} at the end")
    print(f"{'engine':36s} {'median pairs/s':>14s} {'runs (pairs/s)':>32s} {'vs OpenPIV':>10s} "
          f"{'per-run ratio':>13s} {'peak MiB':>9s}")
    for name, _, _ in ENGINES:
        ratio = f"{med[name] / med[ref[name]]:9.1f}x" if name in ref else f"{'-':>10s}"
        # ratio of the two engines' figures within each run (timed minutes apart at most), then the median
        per_run = (f"{np.median(np.array(times[name]) / np.array(times[ref[name]])):12.1f}x" if name in ref
                   else f"{'-':>13s}")
        runs_s = " ".join(f"{v:.2f}" for v in times[name])
        print(f"{name:36s} {med[name]:14.2f} {runs_s:>32s} {ratio} {per_run} {mem[name]:9.0f}")
    return med


def long_clip():
    """Stream a 15 s, 30 fps 1080p clip through analyze; frames are made on the fly, never stored."""
    base = syn.clip(syn.uniform(0, 0), H + 64, W + 64, n_frames=1, density=0.03)[0][1]

    def frames():
        for k in range(450):
            s = int(round(2.4 * k)) % 64  # moves 2.4 px per frame to the left (wraps every 64 px)
            yield k / 30.0, base[32:32 + H, s:s + W]

    tracemalloc.start()
    t0 = time.perf_counter()
    res = analyze(frames(), PivParams(window_px=32, overlap_px=16, averaging="ensemble"))
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    base_mib = base.nbytes / 2**20
    print(f"\n15 s clip, 30 fps, 1080p, ensemble: {res.n_pairs} pairs in {dt:.1f} s "
          f"({res.n_pairs / dt:.1f} pairs/s), tracemalloc peak {peak:.0f} MiB "
          f"(of which the generator's base image {base_mib:.0f} MiB and per-pair fields of "
          f"{res.u_pairs.shape[0]} sampled pairs {(res.u_pairs.nbytes + res.v_pairs.nbytes) / 2**20:.1f} MiB); "
          f"process max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


ACC_ENGINES = [
    ("OpenPIV ESA", dict(engine="openpiv", averaging="mean")),
    ("fieldtool 1 pass", dict(averaging="mean")),
    ("fieldtool ensemble", dict(averaging="ensemble")),
    ("OpenPIV windef 2p", dict(engine="openpiv", averaging="mean", passes=2)),
    ("fieldtool 2 passes", dict(averaging="mean", passes=2)),
]


def accuracy():
    h, w = 384, 512
    cases = syn.accuracy_cases(h, w)
    print(f"\nAccuracy: {w}x{h}, window 32, overlap 16, 3 frames (2 pairs) per case; bias = mean error of u, v (px); "
          "RMS of the vector error (px); valid share")
    head = f"{'case':30s} {'ppp':>6s} {'d px':>5s}"
    for name, _ in ACC_ENGINES:
        head += f" | {name:>24s}"
    print(head)
    worst = {name: 0.0 for name, _ in ACC_ENGINES}
    for k, (disp, dens, diam) in enumerate(cases):
        frames = syn.clip(disp, h, w, n_frames=3, density=dens, diameter=diam, seed=100 + k, dt=1.0)
        line = f"{disp.__name__:30s} {dens:6.3f} {diam:5.1f}"
        for name, kw in ACC_ENGINES:
            with contextlib.redirect_stdout(io.StringIO()):
                res = analyze(frames, PivParams(window_px=32, overlap_px=16, **kw))
            ok = res.valid & ~res.replaced
            tx, ty = disp(res.x[ok], res.y[ok])
            ex, ey = res.u[ok] - tx, res.v[ok] - ty  # dt = 1 s: px/s = px per pair
            rms = float(np.sqrt(np.mean(ex**2 + ey**2))) if ok.any() else float("nan")
            worst[name] = max(worst[name], rms)
            line += f" | {np.mean(ex):+.3f} {np.mean(ey):+.3f} {rms:.3f} {ok.mean():4.0%}"
        print(line)
    print("worst RMS: " + ", ".join(f"{n} {v:.3f}" for n, v in worst.items()))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--ensemble-pairs", type=int, default=150, help="pairs of the clip timed in ensemble mode")
    ap.add_argument("--long", action="store_true", help="also stream a 15 s 1080p clip and report its peak memory")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    a = ap.parse_args()
    if not a.skip_speed:
        speed(a.runs, a.pairs, a.ensemble_pairs)
    if a.long:
        long_clip()
    if not a.skip_accuracy:
        accuracy()


if __name__ == "__main__":
    main()
