"""Temporal denoising for weak-signal clips (dusk, night, haze) that keeps the advected texture.

A centred moving average over ``2 * half + 1`` frames of the (standardised) stream: white sensor noise drops
by sqrt(2 * half + 1); the tracers, moving d px per frame, are smeared by about 2 * half * d px along the flow,
but the filter is the same linear time-invariant operation on both frames of a pair, so the displacement
between them is unchanged (the pair's correlation peak stays where it was, only wider). The frames at the
clip's ends average the frames there are. Streaming: memory ``2 * half + 1`` frames; frames come out in order,
``half`` frames after they went in. Pure numpy.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator

import numpy as np


def temporal_mean(
    frames: Iterable[tuple[float, np.ndarray | None]], half: int = 1, want: Callable[[int], bool] | None = None
) -> Iterator[tuple[float, np.ndarray | None]]:
    """(t_s, frame) -> (t_s, mean of the frames within ``half`` positions, float32). Every input frame must be
    built (no None); ``want(k)``: positions k that fail it come out as (t_s, None) (nothing computed)."""
    return _run(iter(frames), half, want)


def _run(it, half: int, want) -> Iterator[tuple[float, np.ndarray | None]]:
    """Centred mean: window [k - half, k + half] clipped at the ends."""
    items: deque = deque()  # (t, img), positions start at 0
    base = 0  # position of items[0]
    k = 0
    exhausted = False
    while True:
        while not exhausted and base + len(items) - 1 < k + half:
            try:
                t, img = next(it)
            except StopIteration:
                exhausted = True
                break
            if img is None:
                raise ValueError("lowlight.temporal_mean needs every frame built")
            items.append((t, np.asarray(img, np.float32)))
        while base < k - half:
            items.popleft()
            base += 1
        if k - base >= len(items):
            return
        t = items[k - base][0]
        if want is not None and not want(k):
            yield t, None
        else:
            acc = np.zeros_like(items[0][1])
            for _, img in items:
                acc += img
            yield t, acc / np.float32(len(items))
        k += 1


def mask_glints(
    frames: Iterable[tuple[float, np.ndarray | None]],
    median: np.ndarray,
    box: tuple[int, int, int, int],
    threshold: float,
    where: np.ndarray | None = None,
) -> Iterator[tuple[float, np.ndarray | None]]:
    """Per frame, pixels of ``box`` (x0, y0, x1, y1 px) brighter than their temporal ``median`` (grey levels, the
    box's shape) by more than ``threshold`` grey levels are set to that median: short-lived specular glints are
    removed where and when they shine, the tracers between them stay. ``where`` (the box's shape, bool): only
    there (the glare windows of processing/clip_stats.py: bright tracers elsewhere are left alone); None: the
    whole box."""
    x0, y0, x1, y1 = box
    med = np.asarray(median, np.float32)
    for t, img in frames:
        if img is None:
            yield t, img
            continue
        crop = img[y0:y1, x0:x1]
        hot = crop.astype(np.float32) - med > threshold
        if where is not None:
            hot &= where
        if hot.any():
            img = img.copy()
            crop = img[y0:y1, x0:x1]
            crop[hot] = med[hot].astype(crop.dtype)
        yield t, img
