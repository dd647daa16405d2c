"""Masked nodes are not correlated in the final pass, and skipping them changes nothing elsewhere."""

import numpy as np
import pytest
from test_piv import particle_clip, rankine

from fieldtool.processing import piv, piv_engine
from fieldtool.processing.piv import PivParams, analyze


def _count_windows(monkeypatch, side: bool = False) -> list:
    """A list that gets, for each call of ``piv_engine._window_spectra``, the number of windows it transformed (or, with
    ``side``, their side in px)."""
    got = []
    spectra = piv_engine._window_spectra

    def counting(img, oy, ox, lv, size, idx=None):
        got.append(size if side else lv.ny * lv.nx if idx is None else len(idx))
        return spectra(img, oy, ox, lv, size, idx)

    monkeypatch.setattr(piv_engine, "_window_spectra", counting)
    return got


def _mask(h, w):
    m = np.zeros((h, w), bool)
    m[:, :90] = True  # a bank
    m[130:170, 150:200] = True  # a pier
    return m


@pytest.mark.parametrize(
    "averaging,sample", [("ensemble", 30), ("ensemble", 2), ("mean", 30)], ids=["ensemble", "ensemble-sampled", "mean"]
)
def test_skipping_masked_nodes_gives_the_same_vectors(monkeypatch, averaging, sample):
    monkeypatch.setattr(piv, "ENSEMBLE_PAIRS", sample)  # 2: every other pair feeds the ensemble without peaks
    frames = particle_clip(rankine, n_frames=5, seed=3)
    mask = _mask(*frames[0][1].shape)
    params = PivParams(window_px=16, overlap_px=8, passes=2, averaging=averaging)
    calls = _count_windows(monkeypatch)
    skip = analyze(frames, params, mask=mask)
    n_skip = sum(calls)
    calls.clear()
    monkeypatch.setattr(piv_engine, "_SKIP_MASKED", False)
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


def test_nodes_far_from_the_section_are_skipped_and_the_near_ones_unchanged(monkeypatch):
    """``near``: every pass correlates only the nodes within its reach of the section; the final pass' nodes near
    the section read the same as without it, the others have no vector and a NaN valid fraction."""
    from fieldtool.processing.piv_fast import node_reach_px

    frames = particle_clip(rankine, n_frames=5, seed=3)
    h, w = frames[0][1].shape
    params = PivParams(window_px=16, overlap_px=8, passes=2)
    seg = np.array([[40.0, 30.0], [w - 60.0, h - 40.0]])  # a diagonal section
    reach = node_reach_px(16, 8, 2)
    assert reach[0] > reach[1] > 3 * 8
    calls = _count_windows(monkeypatch)
    near = analyze(frames, params, near=([seg], reach))
    n_near = sum(calls)
    calls.clear()
    full = analyze(frames, params)
    n_full = sum(calls)
    assert n_near < 0.8 * n_full
    fin_dist = np.array(
        [
            [
                np.hypot(
                    *(
                        p
                        - seg[0]
                        - np.clip((p - seg[0]) @ (seg[1] - seg[0]) / np.sum((seg[1] - seg[0]) ** 2), 0, 1)
                        * (seg[1] - seg[0])
                    )
                )
                for p in np.stack([x, y], -1)
            ]
            for x, y in zip(full.x, full.y, strict=True)
        ]
    )
    inside = fin_dist <= reach[1]
    assert 0.2 < inside.mean() < 0.8
    assert np.isnan(near.valid_fraction[~inside]).all() and not near.valid[~inside].any()
    assert np.isfinite(near.valid_fraction[inside]).all()
    close = fin_dist <= np.sqrt(2) * 8  # the nodes a section's samples read (bilinear, one spacing)
    ok = close & full.valid & near.valid
    assert ok.sum() > 10 and ok.sum() == close.sum()
    np.testing.assert_allclose(near.u[ok], full.u[ok], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(near.v[ok], full.v[ok], rtol=1e-4, atol=1e-3)


def test_search_area_spectra_only_for_the_frames_that_need_them(monkeypatch):
    """With a search area wider than the window, a frame that is only the first of a selected pair gets no
    search-area spectra and one that is only the second gets no window spectra; the vectors are the same."""
    frames = particle_clip(rankine, n_frames=9, seed=4)
    params = PivParams(window_px=16, overlap_px=8, passes=2, search_px=48)
    sizes = _count_windows(monkeypatch, side=True)
    sel = [0, 3, 6]  # frames 0,3,6 only first, 1,4,7 only second
    res = analyze(iter(frames), params, select=sel)
    # first level: 32 px windows (A, padded to 48), 48 px search areas (B); final level: 16 px windows
    assert sizes.count(48) == 3 and sizes.count(32) == 3 and sizes.count(16) == 3 + 3  # A frames, deformed Bs
    full_prepare = piv_engine._Engine.prepare
    monkeypatch.setattr(
        piv_engine._Engine, "prepare", lambda self, frame, as_a=True, as_b=True: full_prepare(self, frame)
    )
    sizes.clear()
    every = analyze(iter(frames), params, select=sel)
    assert sizes.count(48) == 6 and sizes.count(32) == 6
    np.testing.assert_array_equal(res.u_pairs, every.u_pairs)
    np.testing.assert_array_equal(res.u, every.u)
    assert np.isfinite(res.u).mean() > 0.8


def test_deforming_only_what_the_near_nodes_read_gives_the_same_field(monkeypatch):
    """With ``near``, the second pass deforms frame B only in the rectangles its active windows cover
    (``_Engine._deform_strips``): the field is the one of deforming the whole crop, bit for bit."""
    from fieldtool.processing.piv_fast import node_reach_px

    frames = particle_clip(rankine, n_frames=5, seed=4)
    h, w = frames[0][1].shape
    params = PivParams(window_px=16, overlap_px=8, passes=2)
    seg = np.array([[40.0, 30.0], [w - 60.0, h - 40.0]])  # a diagonal section: a band of active nodes
    near = ([seg], node_reach_px(16, 8, 2))
    share: list = []  # per call, the share of the level's crop the strips cover
    orig = piv_engine._Engine._deform_strips

    def spy(self, k):
        got = orig(self, k)
        lv = self.levels[k]
        whole = (lv.step * (lv.ny - 1) + lv.w) * (lv.step * (lv.nx - 1) + lv.w)
        share.append(1.0 if got is None else sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in got) / whole)
        return got

    monkeypatch.setattr(piv_engine._Engine, "_deform_strips", spy)
    part = analyze(frames, params, near=near)
    assert share and max(share) < 0.9  # the second pass deformed less than its crop
    monkeypatch.setattr(piv_engine._Engine, "_deform_strips", lambda self, k: None)  # the whole crop, as before
    whole = analyze(frames, params, near=near)
    np.testing.assert_array_equal(part.u, whole.u)
    np.testing.assert_array_equal(part.v, whole.v)
    np.testing.assert_array_equal(part.u_pairs, whole.u_pairs)
