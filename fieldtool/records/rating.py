"""Stage-discharge (rating) curve Q = a (h - h0)^b, fitted to (water level, discharge) pairs.

h and h0 in metres (the cross-section's datum), Q in m³/s; ``a`` in m³/s per m^b, ``b`` without unit.
h0 is the level of zero flow and must lie below the lowest measured level.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy.optimize import curve_fit

from fieldtool.errors import ParameterError
from fieldtool.project.model import atomic_write_bytes

B_RANGE = (0.3, 6.0)  # exponents outside this are not a river's control


@dataclass
class RatingCurve:
    """Q = a (h - h0)^b with its fit statistics.

    Attributes
    ----------
    a : coefficient (m³/s at h - h0 = 1 m).
    b : exponent.
    h0 : level of zero flow (m).
    a_se, b_se, h0_se : standard errors from the fit covariance (None when h0 was fixed: h0_se;
        None for all when there are no degrees of freedom left).
    rmse_m3s : root-mean-square residual of Q (m³/s).
    n : number of points.
    h0_fixed : h0 was given, not fitted.
    """

    a: float
    b: float
    h0: float
    a_se: float | None
    b_se: float | None
    h0_se: float | None
    rmse_m3s: float
    n: int
    h0_fixed: bool

    def __call__(self, h) -> np.ndarray:
        """Q (m³/s) at level(s) h (m); 0 at and below h0."""
        d = np.clip(np.asarray(h, float) - self.h0, 0.0, None)
        return self.a * d**self.b

    def level(self, q) -> np.ndarray:
        """The level (m) of discharge(s) q (m³/s): the inverse of the curve."""
        return self.h0 + (np.asarray(q, float) / self.a) ** (1.0 / self.b)

    def describe(self) -> str:
        def pm(v, se, fmt):
            return f"{v:{fmt}}" + (f" ± {se:{fmt}}" if se is not None else "")

        h0 = pm(self.h0, self.h0_se, ".3f") + (" (fixed)" if self.h0_fixed else "")
        return (
            f"Q = a (h - h0)^b with a = {pm(self.a, self.a_se, '.4g')} m3/s, b = {pm(self.b, self.b_se, '.3f')}, "
            f"h0 = {h0} m; rmse {self.rmse_m3s:.4g} m3/s over {self.n} points"
        )


def fit_rating(h, q, h0: float | None = None) -> RatingCurve:
    """Fit Q = a (h - h0)^b by least squares in Q (scipy.optimize.curve_fit).

    Parameters
    ----------
    h : water levels (m).
    q : discharges (m³/s), positive.
    h0 : level of zero flow (m), when known (e.g. the lowest bed point of the control); None = fit
        it, constrained below min(h).

    Returns
    -------
    RatingCurve

    Raises
    ------
    ParameterError : fewer points than parameters, non-positive discharges, a given h0 not below
        every level, or no convergence.
    """
    h = np.asarray(h, float).ravel()
    q = np.asarray(q, float).ravel()
    ok = np.isfinite(h) & np.isfinite(q)
    h, q = h[ok], q[ok]
    n_par = 2 if h0 is not None else 3
    if len(h) < n_par:
        raise ParameterError(
            f"rating curve: {len(h)} measurement(s) with a level and a discharge; "
            f"at least {n_par} are needed{' (or give --h0)' if h0 is None else ''}"
        )
    if np.any(q <= 0):
        raise ParameterError("rating curve: every discharge must be positive; delete or fix the zero/negative ones")
    h_min, h_max = float(h.min()), float(h.max())
    span = max(h_max - h_min, 1e-3)
    if h0 is not None:
        if not h0 < h_min:
            raise ParameterError(f"rating curve: h0 = {h0:.3f} m must be below the lowest level {h_min:.3f} m")
        b0, la0 = _loglin(h - h0, q)
        p0 = [math.exp(la0), float(np.clip(b0, *B_RANGE))]
        bounds = ([0.0, B_RANGE[0]], [np.inf, B_RANGE[1]])
        try:
            popt, pcov = curve_fit(lambda x, a, b: a * (x - h0) ** b, h, q, p0=p0, bounds=bounds, maxfev=20000)
        except (RuntimeError, ValueError) as e:
            raise ParameterError(f"rating curve: the fit did not converge ({e})") from e
        a, b = popt
        res = q - a * (h - h0) ** b
        se = _se(pcov, len(h), 2)
        return RatingCurve(float(a), float(b), float(h0), se[0], se[1], None, _rms(res), len(h), True)

    # start from the best log-linear fit over a grid of h0 below the lowest level
    eps = 1e-4 * span
    best = None
    for d in np.geomspace(eps, 20 * span, 200):
        cand = h_min - d
        b0, la0 = _loglin(h - cand, q)
        if not (B_RANGE[0] <= b0 <= B_RANGE[1]):
            continue
        sse = float(np.sum((q - math.exp(la0) * (h - cand) ** b0) ** 2))
        if best is None or sse < best[0]:
            best = (sse, math.exp(la0), b0, cand)
    if best is None:
        raise ParameterError(
            "rating curve: no power law with an exponent between "
            f"{B_RANGE[0]} and {B_RANGE[1]} fits these points; check the levels and discharges"
        )
    _, a0, b0, c0 = best
    upper_h0 = h_min - eps
    lower_h0 = h_min - 50 * span
    p0 = [a0, b0, float(np.clip(c0, lower_h0, upper_h0))]
    bounds = ([0.0, B_RANGE[0], lower_h0], [np.inf, B_RANGE[1], upper_h0])
    try:
        popt, pcov = curve_fit(_model, h, q, p0=p0, bounds=bounds, maxfev=20000)
    except (RuntimeError, ValueError) as e:
        raise ParameterError(f"rating curve: the fit did not converge ({e})") from e
    a, b, c = popt
    res = q - _model(h, a, b, c)
    se = _se(pcov, len(h), 3)
    return RatingCurve(float(a), float(b), float(c), se[0], se[1], se[2], _rms(res), len(h), False)


def _model(h, a, b, h0):
    return a * np.clip(h - h0, 1e-12, None) ** b


def _loglin(d: np.ndarray, q: np.ndarray) -> tuple[float, float]:
    """(b, ln a) of ln q = ln a + b ln d."""
    x = np.log(d)
    if np.ptp(x) == 0:
        return 1.0, float(np.mean(np.log(q)))
    b, la = np.polyfit(x, np.log(q), 1)
    return float(b), float(la)


def _se(pcov: np.ndarray, n: int, k: int) -> list[float | None]:
    if n <= k or not np.all(np.isfinite(pcov)):
        return [None] * k
    return [float(math.sqrt(max(v, 0.0))) for v in np.diag(pcov)]


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def plot_rating(
    path: Path | str,
    curve: RatingCurve | None,
    h,
    q,
    *,
    ref_h=None,
    ref_q=None,
    site: str = "",
    q_low=None,
    q_high=None,
) -> Path:
    """Stage-discharge plot: the measurements (with their 5-95 % spread when ``q_low``/``q_high``
    are given), the references, and the fitted curve. Written as PNG (or PDF/SVG by suffix)."""
    path = Path(path)
    h = np.asarray(h, float)
    q = np.asarray(q, float)
    fig = Figure(figsize=(7, 5), dpi=110)
    ax = fig.add_subplot()
    if q_low is not None and q_high is not None:
        lo = np.asarray(q_low, float)
        hi = np.asarray(q_high, float)
        good = np.isfinite(lo) & np.isfinite(hi)
        ax.errorbar(
            q[good],
            h[good],
            xerr=[np.clip(q[good] - lo[good], 0, None), np.clip(hi[good] - q[good], 0, None)],
            fmt="none",
            ecolor="tab:blue",
            alpha=0.4,
            capsize=2,
        )
    ax.plot(q, h, "o", color="tab:blue", label=f"LSPIV ({len(q)})")
    if ref_h is not None and ref_q is not None and len(ref_q):
        ax.plot(
            np.asarray(ref_q, float),
            np.asarray(ref_h, float),
            "s",
            mfc="none",
            color="tab:red",
            label=f"reference ({len(ref_q)})",
        )
    if curve is not None:
        top = max(float(np.nanmax(h)) if len(h) else curve.h0 + 1.0, curve.h0 + 1e-3)
        hh = np.linspace(curve.h0, top + 0.1 * (top - curve.h0), 200)
        ax.plot(curve(hh), hh, "-", color="k", label=f"Q = {curve.a:.3g} (h − {curve.h0:.3f})^{curve.b:.2f}")
    ax.set_xlabel("discharge Q (m³/s)")
    ax.set_ylabel("water level h (m)")
    ax.set_xlim(left=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title(f"rating curve{' — ' + site if site else ''}")
    fig.tight_layout()

    buf = io.BytesIO()
    fig.savefig(buf, format=path.suffix.lstrip(".").lower() or "png")
    atomic_write_bytes(path, buf.getvalue())
    return path
