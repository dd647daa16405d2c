"""ffpiv (pyorc's PIV engine) throughput on frames saved by benchmarks/time_to_q.py, in the peers' venv.

``benchmarks/.peers-venv/bin/python ffpiv_rate.py frames.npy WINDOW OVERLAP`` prints one JSON line with the
pairs per second of ``ffpiv.piv_stack`` (numba engine) over the stack's consecutive pairs, after one warm-up
call on the first pair (numba compiles on first use; the compile time is not counted).
"""

import json
import sys
import time

import numpy as np
from ffpiv import piv_stack

imgs = np.load(sys.argv[1])
w, o = int(sys.argv[2]), int(sys.argv[3])
piv_stack(imgs[:2], window_size=(w, w), overlap=(o, o), engine="numba")  # compile
t0 = time.perf_counter()
piv_stack(imgs, window_size=(w, w), overlap=(o, o), engine="numba")
dt = time.perf_counter() - t0
print(json.dumps({"pairs_per_s": (len(imgs) - 1) / dt, "seconds": dt, "pairs": len(imgs) - 1}))
