"""Synthetic PIV image pairs with a known analytic displacement, for benchmarks/piv_vs_openpiv.py.

Particles are Gaussian spots (e^-2 diameter ``diameter`` px, peak ``peak`` grey levels) at uniformly random
positions; frame k+1 holds the same particles moved by ``disp(x, y)`` evaluated at their position in frame k.
The truth at a node is ``disp`` at the node centre (image axes, px per frame pair).
"""

from __future__ import annotations

import numpy as np


def render(h: int, w: int, xs: np.ndarray, ys: np.ndarray, diameter: float = 2.5, peak: float = 180.0) -> np.ndarray:
    """Sum of Gaussian particles on an h x w float32 image."""
    sig = diameter / 4.0
    r = int(np.ceil(3 * sig))
    ix, iy = np.rint(xs).astype(np.int64), np.rint(ys).astype(np.int64)
    img = np.zeros(h * w)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            px, py = ix + dx, iy + dy
            keep = (px >= 0) & (px < w) & (py >= 0) & (py < h)
            val = peak * np.exp(-((px[keep] - xs[keep]) ** 2 + (py[keep] - ys[keep]) ** 2) / (2 * sig * sig))
            img += np.bincount(py[keep] * w + px[keep], weights=val, minlength=h * w)
    return img.reshape(h, w).astype(np.float32)


def clip(disp, h: int, w: int, n_frames: int = 2, density: float = 0.03, diameter: float = 2.5,
         noise: float = 2.0, seed: int = 0, dt: float = 1.0 / 30):
    """List of (t_s, image) frames; ``density`` in particles per pixel."""
    rng = np.random.default_rng(seed)
    pad = 40
    n = int(density * (h + 2 * pad) * (w + 2 * pad))
    xs, ys = rng.uniform(-pad, w + pad, n), rng.uniform(-pad, h + pad, n)
    frames = []
    for k in range(n_frames):
        img = render(h, w, xs, ys, diameter) + rng.normal(0.0, noise, (h, w)).astype(np.float32)
        frames.append((k * dt, np.clip(img, 0, 255).astype(np.float32)))
        dx, dy = disp(xs, ys)
        xs, ys = xs + dx, ys + dy
    return frames


def uniform(dx: float, dy: float):
    def f(x, y):
        return np.full_like(x, dx), np.full_like(y, dy)

    f.__name__ = f"uniform({dx:+.2f}, {dy:+.2f})"
    return f


def shear(h: int, u0: float = 0.5, u1: float = 4.5):
    """u grows linearly from u0 at the top row to u1 at the bottom row; v = 0."""

    def f(x, y):
        return u0 + (u1 - u0) * y / h, np.zeros_like(y)

    f.__name__ = f"shear({u0:g}->{u1:g} px)"
    return f


def rankine(xc: float, yc: float, rc: float = 60.0, vmax: float = 3.5):
    """Rankine vortex: solid-body rotation inside rc, potential flow outside; peak displacement vmax px."""

    def f(x, y):
        dx, dy = x - xc, y - yc
        r = np.hypot(dx, dy) + 1e-9
        vt = np.where(r < rc, vmax * r / rc, vmax * rc / r)
        return -vt * dy / r, vt * dx / r

    f.__name__ = f"rankine(rc={rc:g}, vmax={vmax:g} px)"
    return f


def accuracy_cases(h: int, w: int) -> list:
    """The 8 accuracy cases of the engine tables (piv_vs_openpiv.py, peers/river_accuracy.py) on an h x w frame:
    (displacement, particles per pixel, particle diameter px); case k is rendered with seed 100 + k."""
    cases = []
    for dens, diam in [(0.03, 2.5), (0.01, 2.5), (0.03, 4.0), (0.005, 2.0)]:
        cases.append((uniform(2.35, -1.15), dens, diam))
    for dens, diam in [(0.03, 2.5), (0.01, 3.0)]:
        cases.append((shear(h), dens, diam))
        cases.append((rankine(w / 2, h / 2, rc=60, vmax=3.5), dens, diam))
    return cases
