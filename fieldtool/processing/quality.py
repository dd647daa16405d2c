"""Quality verdict of a measurement: a grade (good / doubtful / unusable) and the reasons, with numbers.

Every check is a small function ``check(ev: Evidence, th: Thresholds) -> list[Reason]`` listed in
:data:`CHECKS`; :func:`assess` runs them all and the grade is the worst severity found. A new check
(e.g. a disagreement between PIV and STIV) is one more function appended to ``CHECKS`` (or passed to
``assess`` as ``extra``), reading an optional field of :class:`Evidence`.

Units: m, s, m/s, m³/s; displacements in px per frame (of the working image); angles in degrees.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from fieldtool.processing.discharge import sample_field

GRADES = ("good", "doubtful", "unusable")


@dataclass
class Reason:
    """Why a measurement is not good. ``value`` and ``threshold`` in the unit the message states."""

    code: str
    severity: str  # doubtful | unusable
    message: str
    value: float | None = None
    threshold: float | None = None

    def to_dict(self) -> dict:
        def f(x):
            return float(x) if x is not None and np.isfinite(x) else None

        return {
            "code": self.code,
            "severity": self.severity,
            "message": self.message,
            "value": f(self.value),
            "threshold": f(self.threshold),
        }


@dataclass
class Quality:
    """The verdict: ``grade`` and its ``reasons`` (empty when good)."""

    grade: str
    reasons: list[Reason] = field(default_factory=list)

    def to_dict(self) -> dict:
        """The ``quality`` key of result.json."""
        return {"grade": self.grade, "reasons": [r.to_dict() for r in self.reasons]}


@dataclass
class Thresholds:
    """Limits of the checks; the project's ``[quality]`` table (same names) documents each one."""

    measured_width_doubtful: float = 0.8  # fraction of the section width with measured (not filled) velocity
    measured_width_unusable: float = 0.4
    valid_fraction_doubtful: float = 0.5  # mean fraction of frame pairs with a valid vector along the section
    valid_fraction_unusable: float = 0.15
    stalled_ratio: float = 0.3  # a subsection slower than this times its moving neighbours' median is stalled
    stalled_width_unusable: float = 0.3  # stalled/upstream share of the width that makes it unusable
    deficit_ratio: float = 0.8  # a subsection below this times the velocity its depth suggests is in deficit
    deficit_q_doubtful: float = 0.03  # discharge the subsections in deficit may miss / Q: doubtful above
    deficit_q_unusable: float = 0.5  # ... unusable above
    displacement_doubtful: float = 0.25  # largest displacement along the section / first-pass window side
    displacement_unusable: float = 0.45
    peak_min: float = 0.15  # median correlation peak (coefficient) along the section
    pair_spread_max: float = 0.35  # robust spread of the per-pair discharges / |Q|
    angle_doubtful_deg: float = 20.0  # mean flow direction off the section normal
    angle_unusable_deg: float = 60.0
    identical_frames_doubtful: float = 0.05  # fraction of consecutive frames that are identical
    identical_frames_unusable: float = 0.5
    min_motion_px: float = 0.1  # median displacement along the section below this (px/frame): no motion
    max_surface_speed_ms: float = 15.0  # faster surface velocity along the section is not a river
    relative_u95_doubtful: float = 0.2  # half-width of the 95 % interval / Q


@dataclass
class Evidence:
    """What the checks read, computed once per run (see :func:`section_evidence`). ``None`` = unknown."""

    subsection_width_m: np.ndarray  # (n,) width of each subsection (m)
    subsection_velocity_ms: np.ndarray  # (n,) measured downstream-normal surface velocity, NaN = filled
    discharge_m3s: float
    subsection_depth_m: np.ndarray | None = None  # (n,) mean depth of each subsection (m)
    valid_fraction_section: float | None = None  # mean over the section's sample points (0..1)
    #: the PIV judged its nodes by their ensemble peak, not by their share of valid single pairs
    #: (``PivParams.min_valid_fraction`` 0: the faint-glare plan, where a glint hides part of every window)
    ensemble_judged: bool = False
    displacement_px: float | None = None  # 95th percentile of |displacement| per frame along the section
    median_displacement_px: float | None = None
    #: with a first guess (``piv.analyze(first_guess=)``): 95th percentile of |displacement - first guess| per
    #: frame along the section, what the first pass had to find around its window offset
    residual_px: float | None = None
    first_window_px: float | None = None  # first-pass window side (px)
    search_px: float | None = None  # first-pass search side (px)
    peak_median: float | None = None  # median correlation peak along the section
    q_pairs_m3s: np.ndarray | None = None  # per-pair discharges (m³/s)
    flow_angle_deg: float | None = None  # mean flow direction off the section normal (deg)
    max_speed_ms: float | None = None  # largest surface speed along the section (m/s)
    identical_frames: float | None = None  # fraction of consecutive frames that were identical
    n_frame_pairs: int | None = None
    relative_u95: float | None = None
    extra: dict = field(default_factory=dict)  # room for other checks' inputs (e.g. STIV velocities)


Check = Callable[[Evidence, Thresholds], list[Reason]]


def _grade2(value: float, doubtful: float, unusable: float, below: bool = True) -> str | None:
    """Severity of ``value`` against two limits (``below``: small values are bad)."""
    if below:
        return "unusable" if value < unusable else ("doubtful" if value < doubtful else None)
    return "unusable" if value > unusable else ("doubtful" if value > doubtful else None)


def check_measured_width(ev: Evidence, th: Thresholds) -> list[Reason]:
    w = np.asarray(ev.subsection_width_m, float)
    meas = np.isfinite(np.asarray(ev.subsection_velocity_ms, float))
    frac = float(w[meas].sum() / w.sum()) if w.sum() > 0 else 0.0
    sev = _grade2(frac, th.measured_width_doubtful, th.measured_width_unusable)
    if sev is None:
        return []
    limit = th.measured_width_unusable if sev == "unusable" else th.measured_width_doubtful
    return [
        Reason(
            "measured_width",
            sev,
            f"only {100 * frac:.0f} % of the section width has a measured velocity (limit {100 * limit:.0f} %); "
            f"{int((~meas).sum())} of {len(w)} subsections were filled from neighbours",
            frac,
            limit,
        )
    ]


def check_valid_fraction(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.valid_fraction_section is None:
        return []
    vf = ev.valid_fraction_section
    sev = _grade2(vf, th.valid_fraction_doubtful, th.valid_fraction_unusable)
    if sev is None:
        return []
    limit = th.valid_fraction_unusable if sev == "unusable" else th.valid_fraction_doubtful
    why = "poor seeding, glare or too strong filters"
    if ev.ensemble_judged and sev == "unusable":  # few single pairs are expected: the ensemble is the measurement
        sev, why = "doubtful", "the nodes were judged by their ensemble peak, as the clip's glare asked"
    return [
        Reason(
            "valid_fraction",
            sev,
            f"along the section only {100 * vf:.0f} % of the frame pairs gave a valid vector (limit "
            f"{100 * limit:.0f} %): {why}",
            vf,
            limit,
        )
    ]


def stalled_subsections(v: np.ndarray, ratio: float = 0.3) -> np.ndarray:
    """Indices of measured subsections near zero or upstream while the river moves downstream.

    A subsection is stalled when the fastest measured subsection on each side of it moves downstream
    faster than ``v / ratio`` (a slow band inside the stream: glints, standing waves), or when it flows
    upstream (below -5 % of the median) while the median moves downstream. ``v`` (m/s), NaN = not measured.
    """
    v = np.asarray(v, float)
    meas = np.isfinite(v)
    if meas.sum() < 3:
        return np.zeros(0, int)
    typical = float(np.median(v[meas]))
    out = []
    for i in np.nonzero(meas)[0]:
        left, right = v[:i][meas[:i]], v[i + 1 :][meas[i + 1 :]]
        ref = min(left.max(), right.max()) if len(left) and len(right) else 0.0
        if (ref > 0 and v[i] < ratio * ref) or (typical > 0 and v[i] < -0.05 * typical):
            out.append(int(i))
    return np.asarray(out, int)


def depth_envelope(v: np.ndarray, depth: np.ndarray, anchor: float = 0.8) -> np.ndarray:
    """Velocity each subsection's depth suggests (m/s): c · depth^(2/3) (Manning, as the thesis fills
    subsections), with c the ``anchor`` quantile of v / depth^(2/3) over the measured subsections, i.e. anchored
    on the best-measured part of the section. NaN where nothing is measured."""
    v, d = np.asarray(v, float), np.asarray(depth, float)
    k = np.where(d > 0, d, np.nan) ** (2.0 / 3.0)
    ok = np.isfinite(v) & np.isfinite(k) & (k > 0)
    if ok.sum() < 3:
        return np.full(len(v), np.nan)
    c = float(np.quantile(v[ok] / k[ok], anchor))
    return np.where(np.isfinite(k), c * np.nan_to_num(k), 0.0) if c > 0 else np.full(len(v), np.nan)


def deficit_subsections(v: np.ndarray, depth: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Indices of measured subsections slower than ``ratio`` times the velocity their depth suggests
    (:func:`depth_envelope`): a band of the section the PIV under-reads (glints, ripples, empty seeding)."""
    v = np.asarray(v, float)
    env = depth_envelope(v, depth)
    with np.errstate(invalid="ignore"):
        bad = np.isfinite(v) & np.isfinite(env) & (env > 0) & (v < ratio * env)
    return np.nonzero(bad)[0]


def check_deficit(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.subsection_depth_m is None:
        return []
    v = np.asarray(ev.subsection_velocity_ms, float)
    w = np.asarray(ev.subsection_width_m, float)
    idx = deficit_subsections(v, ev.subsection_depth_m, th.deficit_ratio)
    if len(idx) == 0:
        return []
    env = depth_envelope(v, ev.subsection_depth_m)
    d = np.asarray(ev.subsection_depth_m, float)
    flux = w * d  # ~ area of each subsection
    total = float(np.nansum(flux * np.where(np.isfinite(v), np.maximum(v, 0.0), 0.0)))
    missing = float(np.sum(flux[idx] * (env[idx] - v[idx])) / total) if total > 0 else float("inf")
    if missing <= th.deficit_q_doubtful:
        return []
    sev = "unusable" if missing > th.deficit_q_unusable else "doubtful"
    limit = th.deficit_q_unusable if sev == "unusable" else th.deficit_q_doubtful
    lst = ", ".join(f"{i + 1} ({v[i]:.2f} of {env[i]:.2f} m/s)" for i in idx[:6]) + (" ..." if len(idx) > 6 else "")
    return [
        Reason(
            "velocity_deficit",
            sev,
            f"subsection(s) {lst} measure less than {100 * th.deficit_ratio:.0f} % of the velocity their depth "
            f"suggests (v ~ depth^(2/3), anchored on the best-measured part): Q may miss up to "
            f"{100 * missing:.0f} % there (limit {100 * limit:.0f} %); the PIV likely under-reads (glints, "
            "ripples, too few tracers, a grazing view)",
            missing,
            limit,
        )
    ]


def check_stalled(ev: Evidence, th: Thresholds) -> list[Reason]:
    """Subsections near zero or upstream while their neighbours move downstream (glints, standing waves)."""
    v = np.asarray(ev.subsection_velocity_ms, float)
    w = np.asarray(ev.subsection_width_m, float)
    stalled = stalled_subsections(v, th.stalled_ratio).tolist()
    if not stalled:
        return []
    share = float(w[stalled].sum() / w.sum()) if w.sum() > 0 else 0.0
    sev = "unusable" if share > th.stalled_width_unusable else "doubtful"
    lst = ", ".join(f"{i + 1} ({v[i]:+.2f} m/s)" for i in stalled[:6]) + (" ..." if len(stalled) > 6 else "")
    return [
        Reason(
            "stalled_subsections",
            sev,
            f"subsection(s) {lst} are near zero or upstream while their neighbours move downstream "
            f"({100 * share:.0f} % of the width): a stationary pattern (sun glints, standing waves) or "
            "wind ripples; try a background filter or mask them",
            share,
            th.stalled_width_unusable,
        )
    ]


def check_displacement(ev: Evidence, th: Thresholds) -> list[Reason]:
    """Displacements close to what the first pass can find (the one-quarter rule and beyond)."""
    if ev.displacement_px is None or not ev.first_window_px:
        return []
    w = float(ev.first_window_px)
    search = float(ev.search_px or w)
    reach = max(w, search)  # side the displacement must stay well inside
    # with a first guess the first pass moved its windows by the first look's field: what it had to find is
    # the residual
    d = ev.displacement_px if ev.residual_px is None else ev.residual_px
    ratio = float(d / reach)
    sev = _grade2(ratio, th.displacement_doubtful, th.displacement_unusable, below=False)
    if sev is None:
        return []
    if ev.residual_px is not None:
        return [
            Reason(
                "displacement_limit",
                sev,
                f"displacements along the section differ from the first look's field by up to "
                f"{d:.1f} px per frame, {100 * ratio:.0f} % of the first-pass window {reach:.0f} px "
                f"(limit {100 * th.displacement_doubtful:.0f} %): the flow changed during the clip or the look "
                "was wrong; set piv.frame_gap and piv.search_px yourself",
                ratio,
                th.displacement_doubtful,
            )
        ]
    need = int(np.ceil(ev.displacement_px / th.displacement_doubtful / 8.0) * 8)
    return [
        Reason(
            "displacement_limit",
            sev,
            f"displacements along the section reach {ev.displacement_px:.1f} px per frame, "
            f"{100 * ratio:.0f} % of the first-pass search side {reach:.0f} px (limit "
            f"{100 * th.displacement_doubtful:.0f} %): too fast for the settings; set piv.search_px to at "
            f"least {need} (or raise piv.window_px / piv.passes)",
            ratio,
            th.displacement_doubtful,
        )
    ]


def check_peak(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.peak_median is None or not np.isfinite(ev.peak_median):
        return []
    if ev.peak_median >= th.peak_min:
        return []
    return [
        Reason(
            "low_correlation",
            "doubtful",
            f"the median correlation peak along the section is {ev.peak_median:.2f} (limit {th.peak_min:.2f}): "
            "the pattern barely matches between frames (sparse tracers, noise, glare)",
            ev.peak_median,
            th.peak_min,
        )
    ]


def check_pair_spread(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.q_pairs_m3s is None:
        return []
    q = np.asarray(ev.q_pairs_m3s, float)
    q = q[np.isfinite(q)]
    if len(q) < 5 or ev.discharge_m3s == 0:
        return []
    p16, p84 = np.percentile(q, [16, 84])
    spread = float(0.5 * (p84 - p16) / abs(ev.discharge_m3s))
    if spread <= th.pair_spread_max:
        return []
    return [
        Reason(
            "pair_spread",
            "doubtful",
            f"the discharge of single frame pairs spreads by ±{100 * spread:.0f} % (limit "
            f"{100 * th.pair_spread_max:.0f} %): unsteady or poorly resolved surface motion",
            spread,
            th.pair_spread_max,
        )
    ]


def check_angle(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.flow_angle_deg is None or not np.isfinite(ev.flow_angle_deg):
        return []
    a = float(ev.flow_angle_deg)
    sev = _grade2(a, th.angle_doubtful_deg, th.angle_unusable_deg, below=False)
    if sev is None:
        return []
    limit = th.angle_unusable_deg if sev == "unusable" else th.angle_doubtful_deg
    return [
        Reason(
            "flow_angle",
            sev,
            f"the flow crosses the section {a:.0f}° off its normal (limit {limit:.0f}°): check the GCP order "
            "and section.points_px, or pick a section across the flow",
            a,
            limit,
        )
    ]


def check_motion(ev: Evidence, th: Thresholds) -> list[Reason]:
    """Identical frames and a surface that does not move."""
    out = []
    if ev.identical_frames is not None and ev.identical_frames > th.identical_frames_doubtful:
        sev = "unusable" if ev.identical_frames > th.identical_frames_unusable else "doubtful"
        n = f" of {ev.n_frame_pairs}" if ev.n_frame_pairs else ""
        out.append(
            Reason(
                "identical_frames",
                sev,
                f"{100 * ev.identical_frames:.0f} %{n} consecutive frame pairs are identical (limit "
                f"{100 * th.identical_frames_doubtful:.0f} %): duplicated frames or a still image; "
                "use the original clip or set video.step",
                ev.identical_frames,
                th.identical_frames_doubtful,
            )
        )
    if ev.median_displacement_px is not None and ev.median_displacement_px < th.min_motion_px:
        out.append(
            Reason(
                "no_motion",
                "unusable",
                f"the surface along the section moves {ev.median_displacement_px:.3f} px per frame (limit "
                f"{th.min_motion_px:g}): no motion was measured (a still image, duplicated frames, the section "
                "not on the water, or a surface too slow for one frame: raise video.step)",
                ev.median_displacement_px,
                th.min_motion_px,
            )
        )
    return out


def check_speed(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.max_speed_ms is None or not np.isfinite(ev.max_speed_ms) or ev.max_speed_ms <= th.max_surface_speed_ms:
        return []
    return [
        Reason(
            "speed_bound",
            "unusable",
            f"a surface velocity of {ev.max_speed_ms:.1f} m/s along the section exceeds "
            f"quality.max_surface_speed_ms = {th.max_surface_speed_ms:g} m/s: check the GCP distances (m, not mm), "
            "the frame timing and the section",
            ev.max_speed_ms,
            th.max_surface_speed_ms,
        )
    ]


def check_interval(ev: Evidence, th: Thresholds) -> list[Reason]:
    if ev.relative_u95 is None or not np.isfinite(ev.relative_u95) or ev.relative_u95 <= th.relative_u95_doubtful:
        return []
    return [
        Reason(
            "wide_interval",
            "doubtful",
            f"the 95 % interval of Q is ±{100 * ev.relative_u95:.0f} % (limit "
            f"{100 * th.relative_u95_doubtful:.0f} %); see the uncertainty budget for its main source",
            ev.relative_u95,
            th.relative_u95_doubtful,
        )
    ]


#: fewer frame pairs than this cannot show the flow is steady nor average out the noise of one pair: doubtful
MIN_PAIRS_GOOD = 5


def check_discharge(ev: Evidence, th: Thresholds) -> list[Reason]:
    """No finite discharge (NaN, infinite, none): unusable, whatever else the checks say."""
    q = ev.discharge_m3s
    if q is not None and np.isfinite(q):
        return []
    return [
        Reason("no_discharge", "unusable", f"the discharge is not a number ({q}); nothing can be reported", None, None)
    ]


def check_pairs(ev: Evidence, th: Thresholds) -> list[Reason]:
    """A clip of fewer than :data:`MIN_PAIRS_GOOD` frame pairs (a 2-frame clip has one): doubtful."""
    n = ev.n_frame_pairs
    if n is None or n >= MIN_PAIRS_GOOD:
        return []
    return [
        Reason(
            "few_pairs",
            "doubtful",
            f"only {n} frame pair(s) (at least {MIN_PAIRS_GOOD} for a good grade): one "
            "pair's noise is not averaged out; use a longer clip",
            float(n),
            float(MIN_PAIRS_GOOD),
        )
    ]


#: reasons that doubt the measured velocities themselves (the interval then allows an under-read)
VELOCITY_DOUBTS = frozenset(
    {
        "stalled_subsections",
        "velocity_deficit",
        "valid_fraction",
        "pair_spread",
        "low_correlation",
        "displacement_limit",
        "no_motion",
        "identical_frames",
    }
)

CHECKS: list[Check] = [
    check_discharge,
    check_pairs,
    check_motion,
    check_speed,
    check_measured_width,
    check_valid_fraction,
    check_stalled,
    check_deficit,
    check_displacement,
    check_peak,
    check_pair_spread,
    check_angle,
    check_interval,
]


def assess(
    ev: Evidence, th: Thresholds | None = None, extra: Iterable[Reason] = (), checks: Iterable[Check] | None = None
) -> Quality:
    """Run every check; the grade is the worst severity among the reasons (good when none).

    Parameters
    ----------
    ev : Evidence
    th : Thresholds, default the documented defaults.
    extra : reasons found elsewhere (e.g. an accepted GCP residual), added as they are.
    checks : the checks to run; default :data:`CHECKS`.
    """
    th = th or Thresholds()
    reasons = list(extra)
    for chk in CHECKS if checks is None else checks:
        reasons.extend(chk(ev, th))
    grade = "good"
    if any(r.severity == "unusable" for r in reasons):
        grade = "unusable"
    elif reasons:
        grade = "doubtful"
    order = {"unusable": 0, "doubtful": 1}
    reasons.sort(key=lambda r: order.get(r.severity, 2))
    return Quality(grade, reasons)


def section_evidence(
    sample_px: np.ndarray,
    normal: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    u_px_s: np.ndarray,
    v_px_s: np.ndarray,
    U_ms: np.ndarray,
    V_ms: np.ndarray,
    dt_s: float,
    valid_fraction: np.ndarray | None = None,
    peak: np.ndarray | None = None,
    first_guess: np.ndarray | None = None,
) -> dict:
    """Field statistics along the section's sample points, as keyword arguments of :class:`Evidence`.

    Parameters
    ----------
    sample_px : (n, k, 2) px sample points of the subsections (working image).
    normal : (2,) downstream unit normal of the section (world).
    x, y : (ny, nx) node centres (px); u_px_s, v_px_s the mean field (px/s); U_ms, V_ms rectified (m/s).
    dt_s : median time between the frames of a pair (s).
    valid_fraction, peak : (ny, nx) per-node fraction of valid pairs and median correlation peak.
    first_guess : (ny, nx, 2) px per pair by which the first pass moved its windows (``PivResult.first_guess``).
    """
    pts = np.asarray(sample_px, float).reshape(-1, 2)
    out: dict = {}
    su, sv = sample_field(x, y, np.asarray(u_px_s, float), np.asarray(v_px_s, float), pts)
    disp = np.hypot(su, sv) * dt_s
    disp = disp[np.isfinite(disp)]
    if len(disp):
        out["displacement_px"] = float(np.percentile(disp, 95))
        out["median_displacement_px"] = float(np.median(disp))
    if first_guess is not None:
        g = np.asarray(first_guess, float)
        gu, gv = sample_field(x, y, g[..., 0], g[..., 1], pts)
        res = np.hypot(su * dt_s - gu, sv * dt_s - gv)
        res = res[np.isfinite(res)]
        if len(res):
            out["residual_px"] = float(np.percentile(res, 95))
    SU, SV = sample_field(x, y, np.asarray(U_ms, float), np.asarray(V_ms, float), pts)
    sp = np.hypot(SU, SV)
    ok = np.isfinite(sp)
    if ok.any():
        out["max_speed_ms"] = float(np.max(sp[ok]))
        n = np.asarray(normal, float)
        vn = SU[ok] * n[0] + SV[ok] * n[1]
        vt = SU[ok] * (-n[1]) + SV[ok] * n[0]
        out["flow_angle_deg"] = float(np.degrees(np.arctan2(abs(vt.mean()), vn.mean())))
    for name, arr in (("valid_fraction_section", valid_fraction), ("peak_median", peak)):
        if arr is None:
            continue
        a = np.asarray(arr, float)
        vals, _ = sample_field(x, y, np.where(np.isfinite(a), a, np.nan), np.zeros_like(a), pts)
        if name == "valid_fraction_section":  # nodes never valid count as 0, not as unknown
            vals, _ = sample_field(x, y, np.nan_to_num(a, nan=0.0), np.zeros_like(a), pts)
        vals = vals[np.isfinite(vals)]
        if len(vals):
            out[name] = float(np.mean(vals) if name == "valid_fraction_section" else np.median(vals))
    return out
