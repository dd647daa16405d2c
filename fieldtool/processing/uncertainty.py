"""Uncertainty of the discharge: bootstrap and Monte Carlo helpers (pure numpy).

Every interval here is a two-sided 95 % interval unless ``level`` says otherwise. Units follow the
values given (m³/s for discharges).
"""

from __future__ import annotations

import numpy as np


def bootstrap_ci(values, level: float = 0.95, n_boot: int = 1000, seed: int = 0,
                 stat=np.mean) -> tuple[float, float]:
    """Percentile-bootstrap interval of ``stat`` (default the mean) of the finite ``values``.

    Parameters
    ----------
    values : array_like
        Samples, e.g. per-pair discharges (m³/s); non-finite ones are ignored.
    level : float
        Coverage of the interval (0..1).
    n_boot : int
        Number of resamples.
    seed : int
        Seed of the resampling, so that a run is reproducible.
    stat : callable
        Statistic along axis 1 of a (n_boot, n) array.

    Returns
    -------
    (lo, hi) : tuple of float
        The interval; (nan, nan) with fewer than two finite values.
    """
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    if len(v) < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(v), (int(n_boot), len(v)))
    s = stat(v[idx], axis=1)
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(s, [a, 1.0 - a])
    return float(lo), float(hi)
