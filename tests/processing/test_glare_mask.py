"""Per-frame glint masking (issue 23): a column of one-frame glints over faint advected tracers.

The glints are known (drawn here), and so are the tracers' displacement: the clip's estimates must see the
glare without reading the glints as tracers, the glints' background must be the water's, the mask must take
the glints and leave the tracers, and the PIV between the masked glints must read the tracers' displacement.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldtool.processing import clip_stats as cs
from fieldtool.processing import lowlight
from fieldtool.processing.piv import PivParams, analyze

H, W = 128, 256
COL = (128, 176)  # the glint column's x range (px)
SPEED = 2.0  # tracers' displacement (px/frame, +x)
LEVEL, AMP, NOISE = 100.0, 8.0, 1.5


def _stack(n=24, glints_per_frame=60, seed=0, amp=AMP):
    """(frames, glint cores): tracers (sigma 1.5 px, peak AMP) moving SPEED px/frame over LEVEL, white noise of
    NOISE, and in COL one-frame glints (sigma 2.2 x 1 px, 150-400 grey levels, clipped at 255) at new places
    in each frame; ``cores[i]``: where frame i's glints add more than 30 grey levels."""
    rng = np.random.default_rng(seed)
    k = int(0.01 * H * W)
    x0, y0 = rng.uniform(0, W, k), rng.uniform(0, H, k)
    frames, cores = [], []
    for i in range(n):
        dots = np.zeros((H, W), np.float32)  # tracers splatted bilinearly, then blurred to sigma 1.5 px
        x = (x0 + SPEED * i) % (W - 1)
        c, fx = np.floor(x).astype(int), (x - np.floor(x)).astype(np.float32)
        r = np.minimum(y0.astype(int), H - 1)
        np.add.at(dots, (r, c), 1 - fx)
        np.add.at(dots, (r, c + 1), fx)
        img = LEVEL + amp * 2 * np.pi * 1.5**2 * cv2.GaussianBlur(dots, (0, 0), 1.5)
        imp = np.zeros((H, W), np.float32)
        gy, gx = rng.integers(0, H, glints_per_frame), rng.integers(*COL, glints_per_frame)
        np.add.at(imp, (gy, gx), rng.uniform(150, 400, glints_per_frame) * 2 * np.pi * 2.2)
        glint = cv2.GaussianBlur(imp, (0, 0), sigmaX=2.2, sigmaY=1.0)
        img += glint + NOISE * rng.standard_normal((H, W)).astype(np.float32)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
        cores.append(glint > 30.0)
    return frames, cores


def _masked(frames, s):
    assert s.median is not None and s.box is not None
    return [
        f for _, f in lowlight.mask_glints(list(enumerate(frames)), s.median, s.box, s.glint_threshold, s.glare_windows)
    ]


def _gates(stats):
    return cs.gates(stats, shrink_default=3.0, min_texture_default=0.05, min_pairs=2, n_frames=24)


def test_estimates_see_the_glare_and_not_the_glints_as_tracers():
    frames, _ = _stack()
    clean, _ = _stack(glints_per_frame=0)
    s, s0 = cs.estimate(frames), cs.estimate(clean)
    assert s.glare_fraction > cs.GLARE_ON and s0.glare_fraction <= cs.GLARE_ON
    assert s.contrast == pytest.approx(s0.contrast, rel=0.35)  # the column's glints do not set the contrast
    g = _gates(s)
    assert g.plan == "low_light+glare" and g.mask_glints and g.shrink == 0.0 and g.min_valid_fraction == 0.0
    assert _gates(s0).min_valid_fraction is None  # no glare: the project's gate stands
    # the glints' background is the water's: the plain median of the column is lifted by the glints
    assert s.median is not None
    col = (slice(None), slice(*COL))
    plain = np.median(np.stack(frames).astype(np.float32), axis=0)
    assert abs(float(np.median(s.median[col])) - LEVEL) < 2 * NOISE < float(np.median(plain[col])) - LEVEL


def test_mask_takes_the_glints_and_leaves_the_tracers():
    frames, cores = _stack()
    s = cs.estimate(frames)
    assert s.median is not None and s.box is not None
    out = _masked(frames, s)
    hit = np.stack([o != f for o, f in zip(out, frames, strict=True)])
    core = np.stack(cores)
    assert hit[core].mean() > 0.95  # the glints' cores, frame by frame
    outside = np.ones((H, W), bool)
    outside[:, COL[0] - 8 : COL[1] + 8] = False
    assert hit[:, outside].mean() < 0.002  # tracers away from the column are left alone


def test_piv_reads_the_tracers_between_the_masked_glints():
    frames, _ = _stack(n=20)
    s = cs.estimate(frames)
    g = _gates(s)
    assert s.median is not None and s.box is not None and g.min_valid_fraction is not None
    masked = _masked(frames, s)
    prm = PivParams(window_px=32, overlap_px=16, passes=1, min_valid_fraction=g.min_valid_fraction)
    read = {}
    for name, src in (("masked", masked), ("raw", frames)):
        res = analyze([(i / 30.0, f.astype(np.float32) - s.median) for i, f in enumerate(src)], prm)
        col = (res.x > COL[0] + 8) & (res.x < COL[1] - 8)  # windows mostly inside the glint column
        u = res.u[col & res.valid] / 30.0
        read[name] = (res.valid[col].mean(), float(np.median(u)) if u.size else np.nan)
    assert read["masked"][0] >= 0.8 and read["masked"][1] == pytest.approx(SPEED, rel=0.05)
    assert read["raw"][0] < 0.5  # the glints unmasked: most of the column is lost


def test_bright_tracers_the_flow_carries_are_not_glints():
    """Tracers 120 grey levels bright, some twice their typical contrast: at a pixel they flicker as glints do, but
    the flow carries them. No glare without glints; with a dense column of glints, only the column is masked."""
    bright, _ = _stack(glints_per_frame=0, amp=120.0)
    s = cs.estimate(bright)
    assert s.glare_windows is None and s.glare_fraction <= cs.GLARE_ON
    frames, _ = _stack(glints_per_frame=200, amp=120.0)
    s = cs.estimate(frames)
    assert s.glare_windows is not None and s.glare_windows[:, COL[0] : COL[1]].all()
    hit = np.stack([o != f for o, f in zip(_masked(frames, s), frames, strict=True)])
    assert not hit[:, :, : COL[0] - 32].any() and not hit[:, :, COL[1] + 32 :].any()
