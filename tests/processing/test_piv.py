"""PIV engine: displacements on synthetic particle images with a known analytic motion.

Particles are Gaussian spots at random positions; frame B holds the same particles moved by a known field
d(x, y) evaluated at their frame-A position. The truth at a node is d at the node centre.
"""

import numpy as np
import pytest

from fieldtool.errors import Cancelled, FieldToolError, InputFileError, ParameterError
from fieldtool.processing import piv, piv_engine
from fieldtool.processing import piv_validate as pv
from fieldtool.processing.piv import PivParams, analyze, grid


def render(h, w, xs, ys, diameter=2.5, peak=180.0):
    """Gaussian particles (e^-2 diameter in px) summed on an h x w float32 image."""
    sig = diameter / 4.0
    r = int(np.ceil(3 * sig))
    off = np.arange(-r, r + 1)
    ix, iy = np.rint(xs).astype(int), np.rint(ys).astype(int)
    img = np.zeros(h * w)
    for dy in off:
        for dx in off:
            px, py = ix + dx, iy + dy
            keep = (px >= 0) & (px < w) & (py >= 0) & (py < h)
            val = peak * np.exp(-((px - xs) ** 2 + (py - ys) ** 2) / (2 * sig * sig))
            img += np.bincount(py[keep] * w + px[keep], weights=val[keep], minlength=h * w)
    return img.reshape(h, w).astype(np.float32)


def particle_clip(disp, h=192, w=256, n_frames=3, density=0.05, diameter=2.5, noise=2.0, seed=0, dts=None):
    """Frames (t, image) of particles advected by ``disp(x, y) -> (dx, dy)`` per frame (px), fresh noise each frame."""
    rng = np.random.default_rng(seed)
    n = int(density * (h + 40) * (w + 40))
    xs, ys = rng.uniform(-20, w + 20, n), rng.uniform(-20, h + 20, n)
    dts = dts or [0.5] * (n_frames - 1)
    t, out = 0.0, []
    for k in range(n_frames):
        img = render(h, w, xs, ys, diameter) + rng.normal(0, noise, (h, w)).astype(np.float32)
        out.append((t, img))
        if k < n_frames - 1:
            dx, dy = disp(xs, ys)
            xs, ys = xs + dx, ys + dy
            t += dts[k]
    return out


def uniform(dx, dy):
    return lambda x, y: (np.full_like(x, dx), np.full_like(y, dy))


def errors(res, disp, dt=0.5):
    ok = res.valid & ~res.replaced
    tx, ty = disp(res.x[ok], res.y[ok])
    ex, ey = res.u[ok] * dt - tx, res.v[ok] * dt - ty
    e = np.concatenate([ex, ey])
    return float(np.mean(ex)), float(np.mean(ey)), float(np.sqrt(np.mean(e**2)))


@pytest.mark.parametrize("shift", [(0.3, -0.7), (2.6, 1.4), (-4.2, 3.1)])
@pytest.mark.parametrize("passes", [1, 2])
def test_uniform_shift_bias_and_rms(shift, passes):
    disp = uniform(*shift)
    res = analyze(particle_clip(disp, seed=1), PivParams(passes=passes, averaging="mean"))
    bx, by, rms = errors(res, disp)
    assert abs(bx) < 0.05 and abs(by) < 0.05
    assert rms < 0.1
    assert res.valid.mean() > 0.95


def test_sign_and_axis_convention():
    """A pattern moved +3 px in x and -2 px in y between frame 1 and 2 gives u > 0, v < 0 (image axes)."""
    disp = uniform(3.0, -2.0)
    frames = particle_clip(disp, n_frames=2, dts=[0.04], seed=2)
    res = analyze(frames, PivParams(averaging="median"))
    assert np.nanmedian(res.u) == pytest.approx(3.0 / 0.04, rel=0.02)
    assert np.nanmedian(res.v) == pytest.approx(-2.0 / 0.04, rel=0.02)
    assert res.u_pairs.shape == (1,) + res.x.shape
    assert res.t_pairs[0] == pytest.approx(0.02)


def test_dt_comes_from_timestamps():
    """Uneven frame spacing: each pair is divided by its own dt, so a constant speed is recovered."""
    speed = 40.0  # px/s in x
    dts = [0.05, 0.1, 0.025]
    rng = np.random.default_rng(3)
    xs, ys = rng.uniform(-20, 276, 2500), rng.uniform(-20, 212, 2500)
    frames, t = [], 0.0
    for k in range(4):
        frames.append((t, render(192, 256, xs, ys)))
        if k < 3:
            xs = xs + speed * dts[k]
            t += dts[k]
    res = analyze(iter(frames), PivParams(averaging="mean"))
    per_pair = np.nanmedian(res.u_pairs, axis=(1, 2))
    assert np.allclose(per_pair * dts, speed * np.array(dts), atol=0.05)  # px per pair
    assert np.allclose(res.dt_s, dts)
    assert np.allclose(res.t_pairs, [0.025, 0.1, 0.1625])
    assert np.nanmedian(res.u) == pytest.approx(speed, rel=0.03)


@pytest.mark.parametrize("averaging", ["ensemble", "mean", "median"])
def test_averaging_modes_agree_on_a_uniform_shift(averaging):
    disp = uniform(1.7, -0.6)
    res = analyze(particle_clip(disp, n_frames=4, seed=4), PivParams(averaging=averaging))
    bx, by, rms = errors(res, disp)
    assert abs(bx) < 0.05 and abs(by) < 0.05 and rms < 0.1
    assert np.all(res.valid_fraction[res.valid & ~res.replaced] >= 0.3)


def test_ensemble_beats_mean_with_sparse_seeding():
    """About half a particle per window: single planes are mostly noise, their SNR-weighted sum has one peak."""
    disp = uniform(2.3, 1.2)
    frames = particle_clip(disp, n_frames=12, density=0.0005, noise=8.0, seed=5)
    ens = analyze(frames, PivParams(averaging="ensemble"))
    mean = analyze(frames, PivParams(averaging="mean"))
    bx_e, by_e, rms_e = errors(ens, disp)
    bx_m, by_m, rms_m = errors(mean, disp)
    assert ens.valid.mean() >= mean.valid.mean() > 0.4
    assert rms_e < 0.05 and rms_e <= rms_m
    assert np.hypot(bx_e, by_e) <= np.hypot(bx_m, by_m)


def rankine(x, y, xc=128.0, yc=96.0, rc=40.0, vmax=3.0):
    dx, dy = x - xc, y - yc
    r = np.hypot(dx, dy) + 1e-9
    vt = np.where(r < rc, vmax * r / rc, vmax * rc / r)
    return -vt * dy / r, vt * dx / r


def shear(x, y):
    return 0.5 + 3.0 * (y / 192.0), np.zeros_like(y)


@pytest.mark.parametrize("disp", [rankine, shear], ids=["rankine", "shear"])
def test_multipass_improves_non_uniform_flow(disp):
    frames = particle_clip(disp, n_frames=3, seed=6)
    one = analyze(frames, PivParams(window_px=16, overlap_px=8, passes=1, averaging="mean"))
    two = analyze(frames, PivParams(window_px=16, overlap_px=8, passes=2, averaging="mean"))
    _, _, rms1 = errors(one, disp)
    _, _, rms2 = errors(two, disp)
    assert rms2 < 0.15
    assert rms2 <= rms1


def test_search_area_larger_than_window_finds_large_displacement():
    """12 px is out of reach of a 32 px FFT window (valid to < 16 px, unreliable past 8); a 64 px search finds it."""
    disp = uniform(12.4, -3.3)
    frames = particle_clip(disp, seed=7)
    res = analyze(frames, PivParams(window_px=32, overlap_px=16, search_px=64, averaging="median"))
    bx, by, rms = errors(res, disp)
    assert abs(bx) < 0.1 and abs(by) < 0.1 and rms < 0.15


def test_agrees_with_openpiv():
    disp = rankine
    frames = particle_clip(disp, seed=8)
    ours = analyze(frames, PivParams(averaging="mean"))
    theirs = analyze(frames, PivParams(averaging="mean", engine="openpiv"))
    assert np.allclose(ours.x, theirs.x) and np.allclose(ours.y, theirs.y)
    both = ours.valid & theirs.valid
    assert both.mean() > 0.9
    diff = np.hypot(ours.u - theirs.u, ours.v - theirs.v)[both] * 0.5
    assert np.median(diff) < 0.05
    assert np.percentile(diff, 95) < 0.25


def test_openpiv_multipass_engine_same_grid():
    disp = uniform(2.2, 0.8)
    frames = particle_clip(disp, n_frames=2, seed=9)
    res = analyze(frames, PivParams(passes=2, averaging="median", engine="openpiv"))
    x, y = grid(frames[0][1].shape, PivParams(passes=2))
    assert np.array_equal(res.x, x) and np.array_equal(res.y, y)
    bx, by, rms = errors(res, disp)
    assert abs(bx) < 0.05 and abs(by) < 0.05 and rms < 0.1
    with pytest.raises(ParameterError, match="piv.averaging"):
        analyze(frames, PivParams(passes=2, averaging="ensemble", engine="openpiv"))


def test_grid_is_centred_window_centres():
    x, y = grid((100, 200), PivParams(window_px=32, overlap_px=16))
    # 200 px: 11 windows cover 192 px, 8 px left over -> first window starts at 4, centre 4 + 15.5; 100 px: 5 rows
    assert x.shape == (5, 11)
    assert x[0, 0] == 19.5 and np.allclose(np.diff(x[0]), 16)
    x, y = grid((100, 200), PivParams(window_px=32, overlap_px=16), roi=(10, 10, 110, 90))
    assert x.min() - 15.5 >= 10 and x.max() + 16.5 <= 110 and y.min() - 15.5 >= 10 and y.max() + 16.5 <= 90


def test_roi_result_on_grid_and_accurate():
    disp = uniform(1.2, 2.1)
    frames = particle_clip(disp, seed=10)
    roi = (40, 30, 200, 170)
    res = analyze(frames, PivParams(averaging="median"), roi=roi)
    x, y = grid(frames[0][1].shape, PivParams(), roi=roi)
    assert np.array_equal(res.x, x) and np.array_equal(res.y, y)
    assert errors(res, disp)[2] < 0.1


def test_mask_makes_vectors_invalid_and_never_replaced():
    disp = uniform(2.0, 1.0)
    frames = particle_clip(disp, seed=11)
    h, w = frames[0][1].shape
    mask = np.zeros((h, w), bool)
    mask[80:120, 100:150] = True  # a pier: covers some window centres
    res = analyze(frames, PivParams(averaging="mean"), mask=mask)
    inside = mask[np.rint(res.y).astype(int), np.rint(res.x).astype(int)]
    assert inside.sum() >= 4
    assert not res.valid[inside].any() and np.isnan(res.u[inside]).all()
    assert np.isnan(res.u_pairs[:, inside]).all()
    assert not res.replaced[inside].any()
    assert res.valid[~inside].mean() > 0.95
    assert errors(res, disp)[2] < 0.1


def test_outlier_window_rejected_and_average_replaced_from_neighbours():
    """One window shows unrelated particles in every frame: its vectors fail validation, its average is refilled."""
    disp = uniform(2.0, -1.0)
    frames = particle_clip(disp, n_frames=4, seed=12)
    p = PivParams(window_px=32, overlap_px=0, averaging="median", min_valid_fraction=0.5)
    x, y = grid(frames[0][1].shape, p)
    j, i = 3, 4
    x0, y0 = int(x[j, i] - 15.5), int(y[j, i] - 15.5)
    rng = np.random.default_rng(0)
    bad = []
    for t, img in frames:
        other = render(32, 32, rng.uniform(-3, 35, 60), rng.uniform(-3, 35, 60))
        img = img.copy()
        img[y0 : y0 + 32, x0 : x0 + 32] = other  # same statistics, no match with the other frames
        bad.append((t, img))
    res = analyze(bad, p)
    assert res.valid_fraction[j, i] < 0.5
    assert res.replaced[j, i] and res.valid[j, i]
    assert abs(res.u[j, i] * 0.5 - 2.0) < 0.1 and abs(res.v[j, i] * 0.5 + 1.0) < 0.1
    others = np.ones_like(res.valid)
    others[j, i] = False
    assert res.valid_fraction[others].min() == 1.0 and not res.replaced[others].any()


def test_speed_limit_invalidates():
    disp = uniform(3.0, 0.0)
    frames = particle_clip(disp, seed=13)
    x, _ = grid(frames[0][1].shape, PivParams())
    limit = np.where(x > 128, 2.0 / 0.5, np.inf)  # 6 px/s measured; right half limited to 4 px/s
    res = analyze(frames, PivParams(averaging="mean"), max_speed_px_s=limit)
    assert not res.valid[x > 140].any()
    assert res.valid[x < 110].all()


def test_cancel_stops_within_a_pair_and_streams():
    frames = particle_clip(uniform(1.0, 1.0), n_frames=6, seed=14)
    consumed = []

    def gen():
        for f in frames:
            consumed.append(f[0])
            yield f

    calls = []
    with pytest.raises(Cancelled):
        analyze(gen(), PivParams(), progress=lambda d, t: calls.append((d, t)), cancel=lambda: len(calls) >= 2)
    assert calls == [(1, 0), (2, 0)]
    assert len(consumed) <= 5  # stopped within the third pair (one frame read ahead), the last never read


def test_progress_total_and_on_pair():
    frames = particle_clip(uniform(1.0, 0.5), n_frames=3, seed=15)
    calls, pairs = [], []
    analyze(
        frames,
        PivParams(),
        progress=lambda d, t: calls.append((d, t)),
        on_pair=lambda i, t, x, y, u, v, ok: pairs.append((i, t, u.shape, ok.dtype)),
    )
    assert calls == [(1, 2), (2, 2)]
    assert [p[0] for p in pairs] == [0, 1] and pairs[0][1] == pytest.approx(0.25) and pairs[0][3] == np.dtype(bool)


@pytest.mark.parametrize(
    "kw, key",
    [
        (dict(window_px=256), "piv.window_px"),
        (dict(overlap_px=32), "piv.overlap_px"),
        (dict(overlap_px=-1), "piv.overlap_px"),
        (dict(passes=3, window_px=64), "piv.passes"),
        (dict(search_px=16), "piv.search_px"),
        (dict(averaging="mode"), "piv.averaging"),
        (dict(engine="matlab"), "piv.engine"),
        (dict(min_valid_fraction=1.5), "piv.min_valid_fraction"),
        (dict(snr_min=0), "piv.snr_min"),
    ],
)
def test_bad_parameters_name_the_key(kw, key):
    frames = [(0.0, np.zeros((192, 200), np.float32)), (0.1, np.zeros((192, 200), np.float32))]
    with pytest.raises(ParameterError, match=key.replace(".", r"\.")):
        analyze(frames, PivParams(**kw))


def test_window_larger_than_roi_message():
    with pytest.raises(ParameterError) as e:
        grid((1080, 1920), PivParams(window_px=128), roi=(0, 0, 100, 80))
    assert "piv.window_px: 128 px is larger than the ROI (100 x 80 px); use 64 or less" in str(e.value)


def test_bad_frames():
    img = np.zeros((64, 64), np.float32)
    with pytest.raises(ParameterError, match="at least 2"):
        analyze([(0.0, img)], PivParams())
    with pytest.raises(ParameterError, match="at least 2"):
        analyze([], PivParams())
    with pytest.raises(InputFileError, match="timestamps must increase"):
        analyze([(0.0, img), (0.0, img)], PivParams())
    with pytest.raises(InputFileError, match="gray"):
        analyze([(0.0, np.zeros((64, 64, 3)))], PivParams())
    with pytest.raises(InputFileError, match="same size"):
        analyze([(0.0, img), (0.1, np.zeros((64, 80), np.float32))], PivParams())
    assert issubclass(InputFileError, FieldToolError)


def test_featureless_frames_give_no_vectors():
    img = np.full((96, 96), 100, np.uint8)
    res = analyze([(0.0, img), (0.1, img)], PivParams())
    assert not res.valid.any() and np.isnan(res.u).all()


# ------------------------------------------------------------------------------------- validation helpers


def test_normalized_median_test_flags_single_outlier():
    u = np.ones((5, 6)) + 0.01 * np.arange(30).reshape(5, 6)
    v = np.zeros((5, 6))
    u[2, 3] = 5.0
    ok = pv.normalized_median_test(u, v, threshold=2.0)
    assert not ok[2, 3] and ok.sum() == 29


def test_global_std_and_speed_tests():
    rng = np.random.default_rng(0)
    u, v = rng.normal(1, 0.1, (10, 10)), rng.normal(0, 0.1, (10, 10))
    u[3, 3] = 10.0
    assert pv.global_std_test(u, v, 4.0).sum() == 99
    ok = pv.speed_test(u, v, np.full((10, 10), 2.0))
    assert not ok[3, 3] and ok.sum() == 99
    assert pv.speed_test(u, v, None).all()


def test_replace_invalid_only_with_valid_neighbours_and_never_in_mask():
    u = np.ones((5, 5))
    v = np.zeros((5, 5))
    u[2, 2] = np.nan  # hole inside valid data -> filled
    u[0, :] = np.nan  # whole first row gone: its nodes have only 3 valid neighbours
    keep = np.zeros((5, 5), bool)
    keep[4, 4] = True
    u[4, 4] = np.nan
    u2, v2, rep = pv.replace_invalid(u, v, keep_invalid=keep, min_neighbours=5, max_iter=1)
    assert rep[2, 2] and u2[2, 2] == 1.0
    assert not rep[0].any() and np.isnan(u2[0]).all()
    assert not rep[4, 4] and np.isnan(u2[4, 4])


def test_backend_choice_without_gpu_falls_back_to_cpu():
    from fieldtool.processing import piv_gpu

    frames = particle_clip(uniform(1.0, 0.5), n_frames=2, seed=16)
    if not piv_gpu.available():
        with pytest.raises(ParameterError, match="CuPy"):
            analyze(frames, PivParams(), backend="gpu")
    a = analyze(frames, PivParams(), backend="auto")
    b = analyze(frames, PivParams(), backend="cpu")
    assert np.allclose(a.u, b.u, atol=0.01 / 0.5, equal_nan=True)


@pytest.fixture
def numpy_as_cupy(monkeypatch):
    """No GPU here: the CuPy engine runs with NumPy/SciPy in CuPy's place (its logic, not the device)."""
    import types

    import scipy.fft

    from fieldtool.processing import piv_gpu

    fake = types.SimpleNamespace(
        **{
            k: getattr(np, k)
            for k in ("ascontiguousarray", "where", "sqrt", "maximum", "float32", "conj", "asarray", "lib")
        }
    )
    fake.asnumpy = np.asarray
    monkeypatch.setattr(piv_gpu, "_cupy", lambda: (fake, scipy.fft))
    monkeypatch.setattr(piv_gpu, "_CHECKED", None)
    return piv_gpu


def test_gpu_code_path_logic_with_numpy_standing_in_for_cupy(numpy_as_cupy):
    """Run the CuPy engine with NumPy/SciPy in CuPy's place to check its logic (not the device)."""
    piv_gpu = numpy_as_cupy
    assert piv_gpu.available()  # self-check against the CPU engine passed
    frames = particle_clip(rankine, n_frames=3, seed=17)
    for kw in (dict(averaging="ensemble"), dict(averaging="mean", search_px=48)):
        g = analyze(frames, PivParams(**kw), backend="gpu")
        c = analyze(frames, PivParams(**kw), backend="cpu")
        assert np.array_equal(g.valid, c.valid)
        assert np.nanmax(np.abs(g.u - c.u)) * 0.5 < 0.01 and np.nanmax(np.abs(g.v - c.v)) * 0.5 < 0.01


# ------------------------------------------------------------------------------------- engine internals


def _second_peak_reference(plane, ky, kx, span):
    """Brute force: highest value >= its 8 neighbours (region circular) outside the 5 x 5 block of the first peak."""
    s = plane.shape[0]
    best = -np.inf
    for y in range(span):
        for x in range(span):
            if ((y - ky) % s in (0, 1, 2, s - 1, s - 2)) and ((x - kx) % s in (0, 1, 2, s - 1, s - 2)):
                continue
            nb = [plane[(y + dy) % span, (x + dx) % span] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
            if plane[y, x] >= max(nb):
                best = max(best, plane[y, x])
    return best


@pytest.mark.parametrize("s, margin, blur", [(16, 0, 0.0), (16, 0, 1.5), (24, 4, 1.5)])
def test_second_peak_is_highest_other_local_maximum(s, margin, blur):
    """Broad, elongated first peaks (blurred noise): the shoulder next to the first peak is never the second peak."""
    import scipy.ndimage as ndi

    rng = np.random.default_rng(21)
    planes = rng.normal(size=(60, s, s))
    if blur:
        planes = ndi.gaussian_filter(planes, (0, blur, 2.5 * blur), mode="wrap")
    planes = (planes - planes.mean(axis=(1, 2), keepdims=True)).astype(np.float32)
    before = planes.copy()
    pk = piv_engine._find_peaks(planes, margin)
    assert np.array_equal(planes, before)  # planes left as they were
    span = 2 * margin + 1 if margin else s
    for i in np.flatnonzero(pk.ok):
        ky, kx = np.unravel_index(np.argmax(planes[i, :span, :span]), (span, span))
        p2 = _second_peak_reference(planes[i], ky, kx, span)
        assert pk.snr[i] == pytest.approx(
            min(planes[i, ky, kx] / p2, piv_engine._SNR_CAP) if p2 > 0 else piv_engine._SNR_CAP, rel=1e-6
        )


@pytest.mark.parametrize("sized", [True, False])
def test_ensemble_keeps_evenly_spaced_pair_sample(monkeypatch, sized):
    """Ensemble mode correlates every pair into the sum but keeps per-pair vectors only on a sample of pairs."""
    monkeypatch.setattr(piv, "ENSEMBLE_PAIRS", 2)
    disp = uniform(1.4, -0.8)
    frames = particle_clip(disp, n_frames=10, seed=22)  # 9 pairs
    src = frames if sized else iter(frames)
    res = analyze(src, PivParams(averaging="ensemble"))
    # known length: every 9 // 2 = 4th pair; unknown: stride 1 -> 2 (at 4 kept) -> 4 (at 4 kept again)
    assert res.n_pairs == 9
    assert list(res.pair_index) == [0, 4, 8]
    assert res.u_pairs.shape == (3,) + res.x.shape and len(res.t_pairs) == 3 and len(res.dt_s) == 3
    assert np.allclose(res.t_pairs, [0.25, 2.25, 4.25])
    bx, by, rms = errors(res, disp)
    assert abs(bx) < 0.05 and abs(by) < 0.05 and rms < 0.1
    full = analyze(frames, PivParams(averaging="mean"))
    assert full.u_pairs.shape[0] == 9 and full.n_pairs == 9


def test_gpu_code_path_ensemble_sample_with_numpy_standing_in_for_cupy(numpy_as_cupy, monkeypatch):
    """As above, with pairs whose cross-spectra go to the ensemble without peaks (correlate(peaks=False))."""
    monkeypatch.setattr(piv, "ENSEMBLE_PAIRS", 2)
    frames = particle_clip(rankine, n_frames=7, seed=23)
    g = analyze(frames, PivParams(averaging="ensemble"), backend="gpu")
    c = analyze(frames, PivParams(averaging="ensemble"), backend="cpu")
    assert list(g.pair_index) == list(c.pair_index) == [0, 3]
    assert np.array_equal(g.valid, c.valid)
    assert np.nanmax(np.abs(g.u - c.u)) * 0.5 < 0.01 and np.nanmax(np.abs(g.v - c.v)) * 0.5 < 0.01


def test_openpiv_ensemble_over_many_pairs():
    """The OpenPIV engine has no spectrum-only correlation: a clip long enough for the ensemble's sample of pairs
    (more than 2 * ENSEMBLE_PAIRS) is correlated pair by pair (it raised a TypeError)."""
    n = 2 * piv.ENSEMBLE_PAIRS + 5
    frames = particle_clip(lambda x, y: (np.full_like(x, 3.0), np.full_like(y, -1.0)), h=96, w=128, n_frames=n, seed=4)
    res = analyze(frames, PivParams(window_px=32, overlap_px=16, engine="openpiv", averaging="ensemble"))
    assert res.n_pairs == n - 1
    assert np.nanmedian(res.u) == pytest.approx(3.0 / 0.5, abs=0.1)  # 3 px per 0.5 s frame to the right
    assert np.nanmedian(res.v) == pytest.approx(-1.0 / 0.5, abs=0.1)
