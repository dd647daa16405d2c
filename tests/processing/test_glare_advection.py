"""Glare windows by advection (issue 23): the flow carries the tracers' bright events, not the glints'.

Tracers and glints both light a pixel for about one frame when the tracers are fast; what sets them apart is
that a tracer's blob is found again in the next frame, displaced as the others of its window are, and a glint
is not (it appears at a new place, or flickers where it was). The scenes are drawn here, so which window holds
what is known.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fieldtool.processing import clip_stats as cs

H, W = 128, 256
LEVEL, NOISE = 100.0, 1.5


def _tracers(rng, n, speed, amp, density=0.01):
    """(n, H, W) float32: Gaussian blobs (sigma 1.5 px, peak ``amp``) moving ``speed`` px/frame (+x)."""
    k = int(density * H * W)
    x0, y0 = rng.uniform(0, W, k), rng.integers(0, H, k)
    out = np.zeros((n, H, W), np.float32)
    for i in range(n):
        x = (x0 + speed * i) % (W - 1)
        c, fx = np.floor(x).astype(int), (x - np.floor(x)).astype(np.float32)
        np.add.at(out[i], (y0, c), 1 - fx)
        np.add.at(out[i], (y0, c + 1), fx)
        out[i] = amp * 2 * np.pi * 1.5**2 * cv2.GaussianBlur(out[i], (0, 0), 1.5)
    return out


def _glints(rng, n, cols, per_frame, in_place=False):
    """(n, H, W) float32: glints (sigma 2.2 x 1 px, 150-400 grey levels) in the columns ``cols`` (x0, x1 px):
    at new places each frame, or (``in_place``) at fixed places, each lit in a frame with probability 0.35."""
    out = np.zeros((n, H, W), np.float32)
    gy, gx = rng.integers(0, H, per_frame), rng.integers(*cols, per_frame)
    for i in range(n):
        if not in_place:
            gy, gx = rng.integers(0, H, per_frame), rng.integers(*cols, per_frame)
        lit = rng.uniform(size=per_frame) < (0.35 if in_place else 1.0)
        imp = np.zeros((H, W), np.float32)
        np.add.at(imp, (gy[lit], gx[lit]), rng.uniform(150, 400, int(lit.sum())) * 2 * np.pi * 2.2)
        out[i] = cv2.GaussianBlur(imp, (0, 0), sigmaX=2.2, sigmaY=1.0)
    return out


def _frames(layers, rng):
    img = LEVEL + sum(layers) + NOISE * rng.standard_normal(layers[0].shape).astype(np.float32)
    return list(np.clip(img, 0, 255).astype(np.uint8))


def _events(frames):
    st = np.stack(frames).astype(np.float32)
    return st - np.median(st, axis=0) > cs.GLARE_K * NOISE


@pytest.mark.parametrize("speed", [1.5, 12.0])
def test_tracers_are_carried_slow_or_fast(speed):
    rng = np.random.default_rng(1)
    ev = _events(_frames([_tracers(rng, 20, speed, 60.0)], rng))
    shares = [cs.carried_share(ev, (r, c, 64), cs.CARRY_REACH) for r in (0, 64) for c in (64, 128)]
    assert all(s is not None and s >= cs.GLARE_CARRIED for s in shares), shares


@pytest.mark.parametrize("in_place", [False, True])
def test_glints_are_not_carried(in_place):
    rng = np.random.default_rng(2)
    n = 20
    layers = [_tracers(rng, n, 2.0, 5.0), _glints(rng, n, (0, W), 150 if in_place else 400, in_place)]
    ev = _events(_frames(layers, rng))
    shares = [cs.carried_share(ev, (r, c, 64), cs.CARRY_REACH) for r in (0, 64) for c in (0, 64, 128, 192)]
    assert all(s is not None and s < cs.GLARE_CARRIED for s in shares), shares


def test_few_events_are_not_judged():
    rng = np.random.default_rng(3)
    ev = _events(_frames([_tracers(rng, 20, 2.0, 5.0)], rng))  # faint tracers: hardly any event at 8 noise sd
    assert cs.carried_share(ev, (0, 0, 64), cs.CARRY_REACH) is None


def test_dense_glints_over_most_windows_do_not_set_the_contrast():
    """A glint column over six of the box's eight windows (the majority: the median over the windows would be a
    glint's), faint tracers: the contrast is the tracers', as without the glints, and the glare is seen."""
    rng = np.random.default_rng(4)
    n = 20
    tr = _tracers(rng, n, 2.0, 8.0)
    with_glints = cs.estimate(_frames([tr, _glints(rng, n, (96, W), 60)], rng))
    clean = cs.estimate(_frames([tr], rng))
    assert with_glints.contrast == pytest.approx(clean.contrast, rel=0.35)
    assert with_glints.cnr < cs.CNR_WEAK and with_glints.glare_fraction > cs.GLARE_ON


def test_fast_tracers_are_not_taken_for_glare():
    """Tracers at 12 px a frame light a pixel for one frame only: their contrast stands, no glare."""
    rng = np.random.default_rng(5)
    fast = cs.estimate(_frames([_tracers(rng, 20, 12.0, 60.0)], rng))
    slow = cs.estimate(_frames([_tracers(rng, 20, 1.5, 60.0)], rng))
    assert fast.contrast == pytest.approx(slow.contrast, rel=0.35) and fast.cnr > cs.CNR_WEAK
