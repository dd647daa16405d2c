"""Which nodes of a PIV field are on the water, for the PIV step's summary and arrows.

Before a section of interest exists nothing says where the water edges are in the image, so the water is
what moves: a node is on the water when its mean vector is valid in at least ``MIN_VALID`` of the frame
pairs and its speed is at least ``MIN_SHARE`` of the field's 90th percentile speed. Banks, walls and the
sky correlate with (almost) no displacement, or not at all, and are left out: the median speed is that of
the water, not of every node (a field half on the banks gave a median of 0.021 m/s), and the banks draw no
arrow. Speeds in the units of ``u``, ``v`` (px/s or m/s).
"""

from __future__ import annotations

import numpy as np

MIN_VALID = 0.3  # fraction of the frame pairs in which a node's vector is valid
MIN_SHARE = 0.2  # of the 90th percentile speed of the valid nodes


def water_nodes(u: np.ndarray, v: np.ndarray, valid_fraction: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask (same shape as ``u``) of the nodes judged on the water (see the module docstring)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    speed = np.hypot(u, v)
    ok = np.isfinite(speed)
    if valid_fraction is not None:
        vf = np.asarray(valid_fraction, float)
        if vf.shape == speed.shape:
            ok &= np.nan_to_num(vf, nan=0.0) >= MIN_VALID
    if not ok.any():
        return ok
    top = float(np.percentile(speed[ok], 90))
    if top <= 0:
        return np.zeros_like(ok)
    return ok & (speed >= MIN_SHARE * top)


def water_median(speed: np.ndarray, water: np.ndarray) -> float | None:
    """Median of ``speed`` over the water nodes; None when there are none."""
    s = np.asarray(speed, float)[water]
    s = s[np.isfinite(s)]
    return float(np.median(s)) if s.size else None
