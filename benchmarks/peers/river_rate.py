"""RIVeR's PIV engine throughput on frames saved by benchmarks/time_to_q.py, in RIVeR's own venv.

``benchmarks/.river-venv/bin/python river_rate.py frames.npy [N]`` prints one JSON line with the pairs per
second over the stack's first N consecutive pairs (all by default) of RIVeR's ``piv_fftmulti`` (river-cli, a
Python port of PIVlab 2.6's ``piv_FFTmulti``), called as RIVeR's own ``piv_loop`` calls it (a mask of ones,
the whole frame as the bbox ``[x, y, width, height]``, its default filters: standard deviation, median test,
inpainting, smoothing):

- ``32->32``: window 32, step 16, ``multipass=False``. RIVeR's function always runs a second
  pass over the deformed second image; without multipass that pass keeps the first window (32 -> 32). RIVeR has
  no single-pass call.
- ``64->32``: window 64 then 32 (``multipass=True``, ``interrogation_area_2=32``), step 32 then 16.

A warm-up call on a 256 x 256 crop of the first pair first (numba compiles its functions then; not counted).

Where its time goes: ``inpaint_nans``, called on the first pass' field, fits two radial basis functions
(``scipy.interpolate.Rbf``, cubic and inverse) through every valid node, each a dense solve of N x N: at window 32
/ step 16 on a 1080p frame N is about 8000 nodes (97 % of the call's time); at window 64 / step 32, about 2000.
"""

import json
import sys
import time

import numpy as np
from river.core.piv_fftmulti import piv_fftmulti

#: RIVeR's two calls (keyword arguments of ``piv_fftmulti``), also those of peers/river_accuracy.py
CONFIGS = {
    "32->32": dict(interrogation_area_1=32, interrogation_area_2=32, multipass=False, step=16),
    "64->32": dict(interrogation_area_1=64, interrogation_area_2=32, multipass=True, step=32),
}


def main():
    imgs = np.load(sys.argv[1])
    if len(sys.argv) > 2:
        imgs = imgs[: int(sys.argv[2]) + 1]
    h, w = imgs.shape[1:]
    mask = np.ones((h, w), np.uint8)
    out = {"pairs": len(imgs) - 1}
    for name, kw in CONFIGS.items():
        piv_fftmulti(imgs[0][:256, :256], imgs[1][:256, :256], mask=mask[:256, :256], bbox=[0, 0, 256, 256], **kw)
        t0 = time.perf_counter()  # after the warm-up on a crop above (numba compiles its functions then)
        for a, b in zip(imgs[:-1], imgs[1:], strict=True):
            piv_fftmulti(a, b, mask=mask, bbox=[0, 0, w, h], **kw)
        out[name] = (len(imgs) - 1) / (time.perf_counter() - t0)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
