"""OpenPIV 0.26 throughput with a chosen backend on frames saved by benchmarks/time_to_q.py, in the peers' venv.

``benchmarks/.peers-venv/bin/python openpiv_rate.py frames.npy BACKEND`` prints one JSON line with the pairs
per second over the stack's consecutive pairs of: one pass of ``extended_search_area_piv`` (window 32,
overlap 16, search 32, peak-to-peak s2n, Gaussian subpixel) and two passes of ``windef.simple_multipass``
(64/32 -> 32/16), both with ``backend`` = rust, auto or scipy. One warm-up pair first (not counted).
"""

import contextlib
import io
import json
import sys
import time

import numpy as np
from openpiv import pyprocess, windef
from openpiv.settings import PIVSettings

imgs = np.load(sys.argv[1])
backend = sys.argv[2]


def single(a, b):
    pyprocess.extended_search_area_piv(a, b, window_size=32, overlap=16, search_area_size=32,
                                       sig2noise_method="peak2peak", subpixel_method="gaussian", backend=backend)


st = PIVSettings()
st.windowsizes, st.overlap, st.num_iterations = (64, 32), (32, 16), 2
st.backend = backend


def two(a, b):
    with contextlib.redirect_stdout(io.StringIO()):
        windef.simple_multipass(a, b, st)


out = {"backend": backend, "pairs": len(imgs) - 1}
for name, fn in (("single_pairs_per_s", single), ("two_pass_pairs_per_s", two)):
    fn(imgs[0], imgs[1])  # warm-up
    t0 = time.perf_counter()
    for a, b in zip(imgs[:-1], imgs[1:]):
        fn(a, b)
    out[name] = (len(imgs) - 1) / (time.perf_counter() - t0)
print(json.dumps(out))
