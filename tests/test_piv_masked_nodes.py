"""Masked nodes are not correlated in the final pass, and skipping them changes nothing elsewhere."""

import numpy as np
import pytest

from fieldtool.processing import piv
from fieldtool.processing.piv import PivParams, analyze

from tests.test_piv import particle_clip, rankine


def _mask(h, w):
    m = np.zeros((h, w), bool)
    m[:, :90] = True  # a bank
    m[130:170, 150:200] = True  # a pier
    return m


@pytest.mark.parametrize("averaging,sample", [("ensemble", 30), ("ensemble", 2), ("mean", 30)],
                         ids=["ensemble", "ensemble-sampled", "mean"])
def test_skipping_masked_nodes_gives_the_same_vectors(monkeypatch, averaging, sample):
    monkeypatch.setattr(piv, "ENSEMBLE_PAIRS", sample)  # 2: every other pair feeds the ensemble without peaks
    frames = particle_clip(rankine, n_frames=5, seed=3)
    mask = _mask(*frames[0][1].shape)
    params = PivParams(window_px=16, overlap_px=8, passes=2, averaging=averaging)
    calls = []
    spectra = piv._window_spectra

    def counting(img, oy, ox, lv, size, idx=None):
        calls.append(lv.ny * lv.nx if idx is None else len(idx))
        return spectra(img, oy, ox, lv, size, idx)

    monkeypatch.setattr(piv, "_window_spectra", counting)
    skip = analyze(frames, params, mask=mask)
    n_skip = sum(calls)
    calls.clear()
    monkeypatch.setattr(piv, "_SKIP_MASKED", False)
    full = analyze(frames, params, mask=mask)
    n_full = sum(calls)
    inside = mask[np.rint(full.y).astype(int), np.rint(full.x).astype(int)]
    assert inside.mean() > 0.3
    assert n_skip < 0.85 * n_full  # fewer windows transformed: the masked final-pass nodes are skipped
    np.testing.assert_array_equal(skip.valid, full.valid)
    np.testing.assert_array_equal(skip.replaced, full.replaced)
    ok = full.valid
    assert ok[~inside].mean() > 0.9
    np.testing.assert_allclose(skip.u[ok], full.u[ok], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(skip.v[ok], full.v[ok], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(skip.u_pairs, full.u_pairs, rtol=1e-5, atol=1e-5, equal_nan=True)
    np.testing.assert_allclose(skip.v_pairs, full.v_pairs, rtol=1e-5, atol=1e-5, equal_nan=True)
    assert np.isnan(skip.u[inside]).all() and not skip.valid[inside].any()
