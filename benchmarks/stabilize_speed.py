"""Stabilisation speed on 720p frames (frames per second of Stabilizer.register).

A synthetic 1280 x 720 scene (textured banks, a band of water flowing at 3 px/frame) is shaken by a
random translation (up to ±6 px) and rotation (up to ±0.5°) per frame; the frames are rendered
first, then only ``register`` is timed. Prints the median over runs, and the ratio to real time at
25 and 30 frames/s. Also prints the residual motion report of the last run.

    .venv/bin/python benchmarks/stabilize_speed.py [--frames 100] [--runs 5] [--model homography]
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np

from fieldtool.processing.stabilize import Stabilizer


def texture(h: int, w: int, rng: np.random.Generator, sigma: float) -> np.ndarray:
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    t = (t - t.min()) / (t.max() - t.min())
    return (40 + 180 * t).astype(np.float32)


def shaky_frames(n: int, h: int = 720, w: int = 1280, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    bank = texture(h, w, rng, 2.0)
    water = texture(h, w + 3 * n + 20, rng, 2.5)
    y0, y1 = h // 3, 2 * h // 3
    out = []
    for t in range(n):
        s = bank.copy()
        s[y0:y1] = water[y0:y1, 3 * t: 3 * t + w]
        M = cv2.getRotationMatrix2D((w / 2, h / 2), rng.uniform(-0.5, 0.5), 1.0) if t else np.eye(2, 3)
        if t:
            M[:, 2] += rng.uniform(-6, 6, 2)
        out.append(cv2.warpAffine(s, M, (w, h), borderMode=cv2.BORDER_REFLECT).astype(np.uint8))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--model", default="homography", choices=("homography", "affine"))
    a = ap.parse_args()
    frames = shaky_frames(a.frames)
    h, w = frames[0].shape
    regions = [[20, 20, w // 2 - 20, h // 3 - 20], [w // 2 + 20, 20, w - 20, h // 3 - 20],
               [20, 2 * h // 3 + 20, w // 2 - 20, h - 20], [w // 2 + 20, 2 * h // 3 + 20, w - 20, h - 20]]
    fps, cpu_ms = [], []
    report = {}
    for _ in range(a.runs):
        t0, c0 = time.perf_counter(), time.process_time()
        st = Stabilizer(frames[0], regions_px=regions, model=a.model)
        for f in frames:
            st.register(f)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        fps.append(len(frames) / dt)
        cpu_ms.append(1000 * dc / len(frames))
        report = st.report()
    med = statistics.median(fps)
    print(f"stabilise {w}x{h}, {a.model}, {len(frames)} frames x {a.runs} runs: "
          f"median {med:.1f} frames/s wall clock (runs: {', '.join(f'{v:.1f}' for v in fps)})")
    print(f"  CPU time per frame (all threads): median {statistics.median(cpu_ms):.1f} ms")
    print(f"  real-time ratio: {med / 25:.2f}x at 25 fps, {med / 30:.2f}x at 30 fps")
    print(f"  residual motion of stable features: median {report['median_px']:.3f} px, max {report['max_px']:.3f} px, "
          f"largest camera shift corrected {report['max_shift_px']:.1f} px")


if __name__ == "__main__":
    main()
