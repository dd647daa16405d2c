"""The under-read a doubted run's interval allows: measured from STIV's disagreement with PIV where STIV compared
enough subsections, the project's prior otherwise (run/assess.underread_bound, processing/stiv.implied_underread);
and the over-read where STIV reads slower and disagrees, measured the same way, nothing without that evidence
(run/assess.overread_bound, processing/stiv.implied_overread)."""

from types import SimpleNamespace

import numpy as np
import pytest

from fieldtool.processing import quality as ql
from fieldtool.processing import stiv
from fieldtool.processing import uncertainty as un
from fieldtool.project.model import Project
from fieldtool.run import quality as stage
from fieldtool.run.assess import overread_bound, underread_bound


def _dis(rel, d=None):
    rel = list(rel)
    finite = [r for r in rel if r is not None]
    return {
        "discharge_relative": float(np.mean(finite)) if d is None else d,
        "subsections_relative": rel,
        "n_compared": len(finite),
    }


def _doubt(severity="doubtful"):
    return [ql.Reason("valid_fraction", severity, "few valid vectors", 0.3, 0.5)]


def test_stiv_faster_than_piv_bounds_the_under_read_by_its_difference_and_noise():
    rng = np.random.default_rng(0)
    rel = 0.10 + rng.normal(0.0, 0.03, 10)
    out = stiv.implied_underread(_dis(rel))
    d = float(np.mean(rel))
    assert out["stiv_relative"] == pytest.approx(d)
    # Q / (1 - u) reaches STIV's discharge and a little beyond: its own standard error, twice
    assert d / (1 + d) < out["fraction"] < 0.2
    assert out["se"] == pytest.approx(np.std(rel, ddof=1) / np.sqrt(out["n_eff"]))


def test_stiv_slower_than_piv_supports_no_under_read():
    rel = [-0.15, -0.18, -0.12, -0.16, -0.14, -0.17]
    assert stiv.implied_underread(_dis(rel))["fraction"] == 0.0


def test_stiv_that_reads_the_river_upstream_is_no_evidence_and_leaves_the_prior():
    """STIV's discharge over the compared subsections upstream (d <= -1) while PIV's goes downstream: its lines
    followed something else than the river (ripples travelling against it); it bounds nothing."""
    rel = [-0.9, -1.8, -3.5, -3.4, 0.3, 0.3, -3.4, 0.1, 0.1, 17.5, 0.2, -0.1, 0.0, -0.3, -3.4]
    assert stiv.implied_underread(_dis(rel, d=-3.26)) is None
    assert stiv.implied_underread(_dis(rel, d=-0.9)) is not None  # slower, still downstream: evidence


def test_too_few_compared_subsections_leave_the_prior():
    assert stiv.implied_underread(_dis([0.2, None, 0.25, None])) is None
    assert stiv.implied_underread(None) is None
    assert stiv.implied_underread({"discharge_relative": None, "subsections_relative": []}) is None


def test_differences_that_drift_along_the_section_count_fewer_independent_samples():
    """A smooth trend along the section (neighbours alike) has a lag-1 autocorrelation: fewer effective samples,
    a larger standard error than the same values in an order without it."""
    smooth = np.linspace(0.0, 0.2, 12)
    mixed = smooth[[0, 6, 1, 7, 2, 8, 3, 9, 4, 10, 5, 11]]
    a, b = stiv.implied_underread(_dis(smooth)), stiv.implied_underread(_dis(mixed))
    assert a["n_eff"] < 0.5 * b["n_eff"] and a["se"] > b["se"]


def test_a_doubt_takes_stivs_bound_never_wider_than_the_prior():
    p = Project()
    frac, block = underread_bound(p, _doubt(), {"disagreement": _dis([0.05, 0.08, 0.1, 0.07, 0.09])})
    assert 0.05 < frac < p.uncertainty.underread_doubtful
    assert block["source"] == "stiv" and block["reasons"] == ["valid_fraction"] and block["prior"] == 0.5
    far = {"disagreement": _dis([1.5, 1.8, 2.0, 1.7])}  # STIV three times faster: the prior caps it
    assert underread_bound(p, _doubt(), far)[0] == p.uncertainty.underread_doubtful
    assert underread_bound(p, _doubt(), far)[1]["source"] == "prior"


def test_without_stiv_or_when_unusable_the_prior_holds_and_without_doubt_nothing():
    p = Project()
    assert underread_bound(p, _doubt(), None)[0] == p.uncertainty.underread_doubtful
    agree = {"disagreement": _dis([0.0, 0.01, -0.01, 0.0])}
    assert underread_bound(p, _doubt("unusable"), agree)[0] == p.uncertainty.underread_unusable
    assert underread_bound(p, [], agree) == (0.0, None)


def _ar1(rng, n, r):
    x = np.zeros(n)
    x[0] = rng.normal() / np.sqrt(1 - r**2)
    for i in range(1, n):
        x[i] = r * x[i - 1] + rng.normal()
    return x


def test_the_inflation_follows_the_lag1_autocorrelation_of_an_ar1_series():
    rng = np.random.default_rng(1)
    for r_true in (0.0, 0.5, 0.8):
        vif, r = un.ar1_inflation(_ar1(rng, 4000, r_true))
        assert r == pytest.approx(r_true, abs=0.05) and vif == pytest.approx((1 + r) / (1 - r))
    assert un.ar1_inflation([1.0, np.nan, 2.0]) == (1.0, 0.0)


def test_inflated_deviations_give_the_standard_error_of_an_autocorrelated_mean():
    """Over many AR(1) series (r = 0.7), the spread of their means is what the bootstrap over one series' rows
    predicts once its deviations are inflated; over the rows as they are it predicts far less (it counts each
    pair as independent)."""
    rng = np.random.default_rng(2)
    n = 180
    means, naive, inflated = [], [], []
    for _ in range(300):
        x = _ar1(rng, n, 0.7)
        means.append(x.mean())
        naive.append(x.std(ddof=1) / np.sqrt(n))
        y = un.inflate_deviations(x, float(np.sqrt(un.ar1_inflation(x)[0])))
        inflated.append(y.std(ddof=1) / np.sqrt(n))
    true_se = float(np.std(means))
    assert np.median(naive) < 0.6 * true_se
    assert np.median(inflated) == pytest.approx(true_se, rel=0.15)


def test_inflation_keeps_the_mean_and_ignores_nan():
    a = np.arange(10.0)[:, None] * np.ones((1, 3))
    a[0, 0] = np.nan
    b = un.inflate_deviations(a, 2.0)
    assert np.nanmean(b, axis=0) == pytest.approx(np.nanmean(a, axis=0)) and np.isnan(b[0, 0])
    assert b[9, 1] - 4.5 == pytest.approx(2 * (9 - 4.5))
    assert un.inflate_deviations(a, 1.0) is a


def test_the_quality_stage_hands_the_runs_stiv_block_to_the_interval(monkeypatch):
    """run/quality.assess passes the discharge stage's STIV block on, so a doubted run's bound can use it, and
    PIV's own discharge where Q is of other velocities (the interval's draws are scaled to it)."""
    seen = {}

    def fake_assess_run(*args, stiv_block=None, piv_discharge_m3s=None):
        seen["stiv"], seen["piv_q"] = stiv_block, piv_discharge_m3s
        return None, ql.Quality("good")

    monkeypatch.setattr(stage, "assess_run", fake_assess_run)
    block = {"disagreement": _dis([0.1, 0.1, 0.1])}
    q = SimpleNamespace(
        result=None, geom=None, world_u=None, world_v=None, q_pairs=None, stiv=block, robust={}, piv_discharge_m3s=1.5
    )
    vel = SimpleNamespace(piv=None, frame_stats={})
    stage.assess(Project(), None, None, None, vel, q, None, [], [])
    assert seen["stiv"] is block and seen["piv_q"] == 1.5


def test_stiv_disagreeing_by_reading_faster_is_a_doubt_that_stiv_bounds():
    """PIV and STIV disagree and STIV's discharge is the faster: the interval allows PIV's under-read by what STIV
    supports (a wide river read -7.5 % by PIV, +0.3 % by STIV, with an interval of +-7 % that missed). Slower:
    no doubt from it."""
    from fieldtool.run.assess import _stiv_faster

    why = {"code": "piv_stiv_disagree", "severity": "doubtful", "message": "disagree", "value": 0.13, "threshold": 0.05}
    faster = {"disagreement": _dis([0.15, 0.18, 0.12, 0.10, 0.13]), "disagreement_reason": why}
    doubts = _stiv_faster(faster)
    assert [r.code for r in doubts] == ["piv_stiv_disagree"]
    frac, block = underread_bound(Project(), doubts, faster)
    assert block["source"] == "stiv" and 0.13 / 1.13 < frac < 0.5
    slower = {"disagreement": _dis([-0.15, -0.18, -0.12]), "disagreement_reason": why}
    assert _stiv_faster(slower) == [] and _stiv_faster({"disagreement": faster["disagreement"]}) == []
    assert _stiv_faster(None) == []


def test_stiv_slower_than_piv_bounds_the_over_read_by_its_difference_and_noise():
    rng = np.random.default_rng(3)
    rel = -0.12 + rng.normal(0.0, 0.03, 10)
    out = stiv.implied_overread(_dis(rel))
    m = float(np.median(rel))
    # Q (1 - o) reaches STIV's (median) difference and a little beyond: its own standard error, twice
    assert out["stiv_relative"] == pytest.approx(m) and -m < out["fraction"] < 0.25
    assert out["fraction"] == pytest.approx(-m + 2 * out["se"])
    assert stiv.implied_overread(_dis([0.15, 0.18, 0.12, 0.16, 0.14]))["fraction"] == 0.0  # faster: none
    assert stiv.implied_overread(_dis([-0.9, -1.8, -3.5, -3.4], d=-2.4)) is None  # upstream: no evidence


def test_a_few_subsections_where_stiv_fails_make_no_over_read():
    """STIV reads near zero or upstream in a few subsections (ripples against the flow) and agrees elsewhere:
    its discharge reads slower (drawn scene g077: -5 %, PIV right within 2 %), but the median difference is
    PIV's, so the interval is not widened by STIV's failure (by the mean and its spread it was: -50 %)."""
    rel = [0.0, 0.04, 0.05, 0.03, 0.04, 0.03, 0.03, 0.02, 0.01, -1.2, -3.16, -3.76]
    assert stiv.implied_overread(_dis(rel, d=-0.052))["fraction"] < 0.02


def test_stiv_disagreeing_by_reading_slower_is_a_doubt_that_stiv_bounds():
    """PIV and STIV disagree and STIV's discharge is the slower (a hazy 640x480 scene read +27.1 % by PIV,
    +0.1 % by STIV, with an interval of -11 to +10 % that missed): the interval allows PIV's over-read by what
    STIV supports, never beyond the prior; nothing where Q is STIV's own, where STIV reads faster, or where
    the reason is missing."""
    from fieldtool.run.assess import _stiv_slower

    why = {"code": "piv_stiv_disagree", "severity": "doubtful", "message": "disagree", "value": 0.19, "threshold": 0.05}
    slower = {"disagreement": _dis([-0.15, -0.22, -0.18, -0.20, -0.17]), "disagreement_reason": why}
    assert [r.code for r in _stiv_slower(slower)] == ["piv_stiv_disagree"]
    frac, block = overread_bound(Project(), slower)
    assert block["source"] == "stiv" and block["reasons"] == ["piv_stiv_disagree"] and 0.18 < frac < 0.3
    assert block["stiv"]["fraction"] == frac and block["prior"] == 0.5
    far = {"disagreement": _dis([-0.7, -0.8, -0.75, -0.72]), "disagreement_reason": why}
    assert overread_bound(Project(), far)[0] == 0.5 and overread_bound(Project(), far)[1]["source"] == "prior"
    assert overread_bound(Project(), {**slower, "velocity_source_used": "stiv"}) == (0.0, None)
    assert overread_bound(Project(), {"disagreement": slower["disagreement"]}) == (0.0, None)
    faster = {"disagreement": _dis([0.15, 0.18, 0.12]), "disagreement_reason": why}
    assert _stiv_slower(faster) == [] and overread_bound(Project(), faster) == (0.0, None)
    assert overread_bound(Project(), None) == (0.0, None)
