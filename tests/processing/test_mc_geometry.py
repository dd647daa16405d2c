"""The Monte Carlo's batched geometry (processing/mc_geometry.py) against the one-draw functions it replaces:
CrossSection.water_edges / wetted_area, discharge.manning_factors, section_geometry, section_samples."""

import numpy as np
import pytest

from fieldtool.processing import mc_geometry as mg
from fieldtool.processing.cross_section import CrossSection
from fieldtool.processing.discharge import fill_velocity, manning_factors, section_geometry, section_samples
from fieldtool.processing.ortho import OrthoMapping


def _bed(rng, m=14):
    st = np.cumsum(rng.uniform(0.3, 2.0, m))
    z = 101.0 - 2.0 * np.sin(np.linspace(0, np.pi, m)) + rng.normal(0, 0.15, m)
    z[0], z[-1] = 101.5, 101.6
    return CrossSection(st, z)


@pytest.mark.parametrize("seed", range(5))
def test_bed_draws_match_the_cross_section(seed):
    rng = np.random.default_rng(seed)
    cs = _bed(rng)
    n, n_sub = 40, 9
    elev = cs.elevation[None, :] + rng.normal(0, 0.05, (n, len(cs.elevation)))
    level = rng.uniform(cs.bed_min - 0.2, 101.7, n)  # some below the bed, some over a bank: not ok
    bed = mg.bed_draws(cs.station, elev, level, n_sub, None)
    checked = 0
    for i in range(n):
        c = CrossSection(cs.station, elev[i])
        try:
            left, right = c.water_edges(level[i])
        except Exception:  # noqa: BLE001 - the one-draw path refuses this level
            assert not bed.ok[i]
            continue
        assert bed.ok[i]
        e = np.linspace(left, right, n_sub + 1)
        area = [c.wetted_area(level[i], a, b) for a, b in zip(e[:-1], e[1:], strict=True)]
        np.testing.assert_allclose(bed.area_m2[i], area, rtol=1e-9, atol=1e-12)
        to, frm = manning_factors(c, level[i], e)
        np.testing.assert_allclose(bed.law[0][i], to, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(bed.law[1][i], frm, rtol=1e-9, atol=1e-12)
        checked += 1
    assert 10 < checked < n  # both kinds of draw were met


def test_fill_velocity_rows_match_one_row_at_a_time():
    """The (n, n_sub) fill is the 1-D fill of each row: nearest valid subsection, the left one on a tie."""
    rng = np.random.default_rng(0)
    v = rng.normal(1.0, 0.3, (300, 9))
    v[rng.uniform(size=v.shape) < 0.4] = np.nan
    v[0] = np.nan  # a row with nothing valid stays NaN
    to, frm = rng.uniform(0.2, 1.0, v.shape), rng.uniform(0.2, 1.0, v.shape)
    vf, filled = fill_velocity(v, (to, frm))
    for i in range(1, len(v)):
        valid = np.nonzero(np.isfinite(v[i]))[0]
        for k in range(v.shape[1]):
            if np.isfinite(v[i, k]):
                assert vf[i, k] == v[i, k] and not filled[i, k]
            elif len(valid):
                j = valid[np.argmin(np.abs(valid - k))]
                assert vf[i, k] == pytest.approx(v[i, j] * to[i, k] / frm[i, j]) and filled[i, k]
    assert np.isnan(vf[0]).all() and filled[0].all()


def test_section_and_samples_match_one_draw_at_a_time():
    rng = np.random.default_rng(3)
    H0 = np.array([[0.01, 0.002, -3.0], [0.0005, 0.012, -2.0], [1e-6, 4e-5, 1.0]])
    Hs = H0[None] * (1 + rng.normal(0, 0.01, (6, 3, 3)))
    y, x = np.mgrid[100:400:16, 50:700:16].astype(float)
    u, v = rng.normal(3, 1, x.shape), rng.normal(0.5, 0.3, x.shape)
    u[rng.uniform(size=u.shape) < 0.1] = np.nan  # invalid nodes
    pts = np.array([[80.0, 250.0], [650.0, 300.0]])
    cs = _bed(rng)
    sec = mg.section_draws(pts, Hs, 7)
    U, V = mg.rectify_draws(Hs, x, y, u, v)
    vn = mg.normal_samples(sec, x, y, U, V, None)
    Us, Vs = mg.rectify_sampled(Hs, x, y, u, v, sec)  # only the nodes the samples read
    np.testing.assert_array_equal(mg.normal_samples(sec, x, y, Us, Vs, None), vn)
    assert np.isnan(Us).mean() > 0.3  # most of the grid was not rectified
    for i, H in enumerate(Hs):
        mp = OrthoMapping(H, "homography")
        g = section_geometry(pts, mp, cs, 101.0, 7, station_offset_m=0.0)
        np.testing.assert_allclose(sec.sample_img[i], g.sample_img, rtol=1e-10)
        np.testing.assert_allclose(sec.length_m[i], g.length_m, rtol=1e-12)
        Ui, Vi = mp.rectify_velocity(x, y, u, v)
        np.testing.assert_allclose(vn[i], section_samples(g, x, y, Ui, Vi), rtol=1e-10, equal_nan=True)
    assert sec.ok.all()
