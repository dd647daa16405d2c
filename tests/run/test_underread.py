"""The under-read a doubted run's interval allows: measured from STIV's disagreement with PIV where STIV compared
enough subsections, the project's prior otherwise (run/assess.underread_bound, processing/stiv.implied_underread)."""

import numpy as np
import pytest

from fieldtool.processing import quality as ql
from fieldtool.processing import stiv
from fieldtool.project.model import Project
from fieldtool.run.assess import underread_bound


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
