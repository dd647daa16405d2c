"""Facts and guards on the velocities along the section, between PIV and the discharge.

Wind ripples, standing waves and glints give velocities near zero or upstream in a few subsections while the
river moves downstream elsewhere. Such a velocity must never reach the discharge silently: it is rejected here
(NaN, then filled from its neighbours by ``discharge.fill_velocity``, along the local Manning law) and counted, so
that the quality verdict can say how much of the width was measured and how much was filled.
"""

from __future__ import annotations

import numpy as np

#: a subsection is "upstream" below this fraction of the section's median downstream velocity (negative: truly
#: upstream, not merely slow near a bank)
UPSTREAM_FRACTION = -0.05


def reject_upstream(v_sub: np.ndarray, fraction: float = UPSTREAM_FRACTION) -> tuple[np.ndarray, np.ndarray]:
    """Reject subsection velocities that go upstream while the section as a whole goes downstream.

    Parameters
    ----------
    v_sub : (n,) surface velocity normal to the section per subsection (m/s, downstream positive; NaN = none).
    fraction : a velocity below ``fraction * median(valid v_sub)`` is upstream (default -0.05: clearly upstream).

    Returns
    -------
    v : (n,) the velocities with the rejected ones set to NaN.
    rejected : (n,) bool.
    """
    v = np.asarray(v_sub, dtype=float).copy()
    ok = np.isfinite(v)
    rejected = np.zeros(v.shape, bool)
    if ok.sum() < 3:
        return v, rejected
    med = float(np.median(v[ok]))
    if med <= 0:  # the section as a whole does not go downstream: nothing to compare with
        return v, rejected
    rejected = ok & (v < fraction * med)
    v[rejected] = np.nan
    return v, rejected


def width_share(station_from: np.ndarray, station_to: np.ndarray, flags: np.ndarray) -> float:
    """Share (0..1) of the section's width covered by the flagged subsections."""
    w = np.asarray(station_to, float) - np.asarray(station_from, float)
    tot = float(w.sum())
    return float(w[np.asarray(flags, bool)].sum() / tot) if tot > 0 else 0.0
