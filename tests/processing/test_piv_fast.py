"""The fast path: section band, pair order, analyze(select=, carry=), convergence stop, reader thread, pipeline keys."""

import json

import numpy as np
import pytest
from test_piv import particle_clip, uniform

from fieldtool.processing import piv_fast
from fieldtool.processing.piv import PivParams, analyze


def test_pair_order_is_a_permutation_whose_prefixes_spread_over_the_clip():
    for n in (1, 2, 7, 64, 239, 899):
        order = piv_fast.pair_order(n)
        assert sorted(order.tolist()) == list(range(n))
    order = piv_fast.pair_order(239)
    for k in (8, 16, 30, 60):
        gaps = np.diff(np.sort(np.r_[order[:k], 239]))
        assert gaps.max() <= 2 * 239 / k + 1  # no hole longer than two even spacings
        assert order[:k].min() < 239 / k + 1


def test_band_covers_the_segments_with_the_margin_and_stays_in_frame_and_roi():
    seg = np.array([[696.1, 494.5], [898.7, 205.3]])
    m = piv_fast.band_margin_px(32, 16, 2)
    assert m >= 3 * 32 + 32  # three first-pass spacings plus half the first window
    x0, y0, x1, y1 = piv_fast.section_band((720, 1280), [seg], m)
    assert x0 <= 696 - m and x1 >= 899 + m and y0 <= 205 - m and y1 >= 495 + m
    assert (x0, y0) >= (0, 0) and (x1, y1) <= (1280, 720)
    # several sections: the box around all; a ROI limits it
    seg2 = np.array([[100.0, 600.0], [300.0, 650.0]])
    b2 = piv_fast.section_band((720, 1280), [seg, seg2], m)
    assert b2[0] == 0 and b2[3] == 720
    b3 = piv_fast.section_band((720, 1280), [seg], m, roi=(600, 0, 1280, 400))
    assert b3 == (600, max(0, 205 - m), min(1280, 899 + m + 1), 400)
    # too thin: grown to the first window about its centre
    b4 = piv_fast.section_band((720, 1280), [np.array([[500.0, 300.0], [520.0, 300.0]])], 4, min_side_px=128)
    assert b4[2] - b4[0] == 128 and b4[3] - b4[1] == 128
    assert piv_fast.section_band((720, 1280), [], m) == (0, 0, 1280, 720)


@pytest.fixture(scope="module")
def clip():
    return particle_clip(uniform(3.2, -1.4), h=128, w=160, n_frames=9, seed=3)


def test_select_and_carry_give_the_same_field_as_one_call_on_those_pairs(clip):
    p = PivParams(window_px=16, overlap_px=8, passes=2)
    sel_a, sel_b = [0, 4], [2, 6, 7]
    first = analyze(iter(clip), p, select=sel_a)
    assert first.n_pairs == 2 and list(first.pair_index) == sel_a
    both = analyze(iter(clip), p, select=sel_b, carry=first.carry)
    once = analyze(iter(clip), p, select=sel_a + sel_b)
    assert both.n_pairs == once.n_pairs == 5
    assert sorted(both.pair_index.tolist()) == sorted(once.pair_index.tolist())
    np.testing.assert_allclose(both.u, once.u, rtol=1e-5, equal_nan=True)
    np.testing.assert_allclose(both.v, once.v, rtol=1e-5, equal_nan=True)
    ok = both.valid & ~both.replaced
    assert ok.mean() > 0.8
    assert abs(np.median(both.u[ok]) * 0.5 - 3.2) < 0.05 and abs(np.median(both.v[ok]) * 0.5 + 1.4) < 0.05


def test_select_leaves_the_stream_after_the_last_pair_and_transforms_only_needed_frames(clip):
    seen = []

    def frames():
        for k, (t, img) in enumerate(clip):
            seen.append(k)
            yield t, (img if k in (0, 1, 2, 3, 4) else None)  # frames of no selected pair need not be decoded

    res = analyze(frames(), PivParams(window_px=16, overlap_px=8, passes=1), select=[1, 3])
    assert res.n_pairs == 2 and max(seen) <= 5  # pair 3 = frames 3-4; frame 5 read, then the stream is left
    assert list(res.pair_index) == [1, 3]


def test_converge_stops_at_min_pairs_when_the_pairs_agree_and_uses_all_when_they_do_not(clip):
    p = PivParams(window_px=16, overlap_px=8, passes=1)

    def run(frames, select, carry):
        return analyze(frames, p, select=select, carry=carry)

    def q_mean_u(x, y, u, v):
        return float(np.nanmean(u))

    res, info, q = piv_fast.converge(lambda want: iter(clip), 8, run, q_mean_u, rel_ci=0.05, min_pairs=3)
    assert info.converged and info.pairs_used == 3 and info.rounds == 1 and len(q) == 3
    noisy = iter(np.random.default_rng(0).normal(1.0, 0.8, 100))
    res, info, q = piv_fast.converge(lambda want: iter(clip), 8, run, lambda *a: next(noisy), rel_ci=0.01, min_pairs=3)
    assert not info.converged and info.pairs_used == 8 and info.rounds >= 2 and res.carry is None
    assert list(res.pair_index) == list(range(8)) and np.all(np.diff(res.t_pairs) > 0)


def test_prefetch_passes_items_errors_and_stops_on_close():
    assert list(piv_fast.prefetch(iter(range(10)), depth=2)) == list(range(10))

    def bad():
        yield 1
        raise ValueError("broken frame")

    it = piv_fast.prefetch(bad())
    assert next(it) == 1
    with pytest.raises(ValueError, match="broken frame"):
        next(it)
    produced = []

    def endless():
        k = 0
        while True:
            produced.append(k)
            yield k
            k += 1

    it = piv_fast.prefetch(endless(), depth=3)
    assert next(it) == 0
    it.close()
    n = len(produced)
    assert n <= 6 and len(produced) == n  # stopped


def test_pipeline_band_and_convergence_keys_and_cache(scene):
    from fieldtool.project.model import load_project
    from fieldtool.run.pipeline import run_project

    proj = load_project(scene / "project.toml")
    proj.roi.rect_px = []
    proj.piv.min_pairs = 10
    proj.piv.frame_gap = 1  # pairs of consecutive frames: 35 in the 36-frame clip
    # stationary-pattern removal reads every frame; the pairs of the first round are spread over the clip and
    # correlated in that same pass
    std_fast = run_project(proj, None)
    s = std_fast.summary()
    assert isinstance(s["converged"], bool) and 10 <= s["pairs_used"] <= 35 and s["piv_sampling"]["rounds"] >= 1
    assert std_fast.robust["stationary_removed"]["frames"] == 36  # every frame standardised, in one pass
    proj.piv.all_pairs = True
    one_pass = run_project(proj, None)
    assert one_pass.summary()["converged"] is None and one_pass.summary()["pairs_used"] == 35
    assert abs(std_fast.discharge.discharge_m3s / one_pass.discharge.discharge_m3s - 1) < 0.01
    if one_pass.stiv is not None:  # STIV samples its lines from the first round's stream: the whole clip
        assert std_fast.stiv["discharge_m3s"] == pytest.approx(one_pass.stiv["discharge_m3s"], rel=1e-6)
    proj.piv.all_pairs = False
    proj.piv.remove_stationary = False  # rounds that skip frames until the discharge has converged
    fast = run_project(proj, scene / "out")
    d = json.loads((scene / "out" / "result.json").read_text())
    assert d["pairs_used"] == fast.piv.n_pairs and 10 <= d["pairs_used"] <= 35 and isinstance(d["converged"], bool)
    x0, y0, x1, y1 = d["piv_region"]["box_px"]
    assert (x1 - x0) * (y1 - y0) < 0.6 * 1280 * 720  # only the band was correlated
    assert fast.piv.x.min() >= x0 and fast.piv.x.max() <= x1
    # every pair, whole frame: same discharge within a percent
    proj.piv.all_pairs = True
    proj.piv.region = "full"
    full = run_project(proj, scene / "out2")
    d2 = json.loads((scene / "out2" / "result.json").read_text())
    assert d2["pairs_used"] == 35 and d2["converged"] is None and d2["piv_region"]["box_px"] is None
    assert abs(fast.discharge.discharge_m3s / full.discharge.discharge_m3s - 1) < 0.01
    # the band follows the section: moving it recomputes the field; the same project reuses it
    proj.piv.all_pairs, proj.piv.region = False, "section"
    assert run_project(proj, scene / "out").piv_reused
    proj.section.points_px = [[x + 40.0, y] for x, y in proj.section.points_px]
    assert not run_project(proj, scene / "out").piv_reused
    proj.piv.region = "diagonal"
    from fieldtool.errors import ParameterError

    with pytest.raises(ParameterError, match="piv.region"):
        run_project(proj, scene / "out")


def test_frame_source_decodes_past_unwanted_frames_with_the_same_times(short_scene):
    from fieldtool.processing.frames import FrameSource

    src = FrameSource(short_scene.video_path, step=2)
    full = list(src)
    part = list(src.iter_wanted(lambda k: k % 3 == 0))
    assert [f.t_s for f in part] == [f.t_s for f in full] and [f.index for f in part] == [f.index for f in full]
    for k, (a, b) in enumerate(zip(full, part, strict=True)):
        assert (b.image is not None) == (k % 3 == 0)
        if b.image is not None:
            assert np.array_equal(a.image, b.image)


def test_standardize_builds_only_wanted_frames_with_the_same_values():
    from fieldtool.processing import surface

    rng = np.random.default_rng(3)
    frames = [(k / 30, (rng.random((40, 50)) * 200).astype(np.float32)) for k in range(30)]
    full = list(surface.standardize(frames, (5, 5, 40, 30), margin=4, half=5))
    part = list(surface.standardize(frames, (5, 5, 40, 30), margin=4, half=5, want=lambda k: k % 4 == 1))
    assert [t for t, _ in part] == [t for t, _ in full]
    for k, ((_, a), (_, b)) in enumerate(zip(full, part, strict=True)):
        assert (b is None) == (k % 4 != 1)
        if b is not None:
            assert np.array_equal(a, b)


def test_float16_window_storage_agrees_with_float32(monkeypatch):
    """Boxes too large for a float32 window keep it as float16: the frames differ only by that rounding."""
    from fieldtool.processing import surface

    rng = np.random.default_rng(1)
    frames = [(k / 30, (rng.random((40, 50)) * 200).astype(np.float32)) for k in range(30)]
    f32 = list(surface.standardize(frames, (5, 5, 40, 30), margin=4, half=5))
    monkeypatch.setattr(surface, "WINDOW_BYTES_F32", 0)
    f16 = list(surface.standardize(frames, (5, 5, 40, 30), margin=4, half=5))
    for (ta, a), (tb, b) in zip(f32, f16, strict=True):
        assert ta == tb and a.dtype == b.dtype == np.float32
        assert np.abs(a - b).max() < 0.01 * max(np.abs(a).max(), 1.0)
        assert not np.array_equal(a, b) or not a.any()


def _standardized_by_the_formula(frames, box, half, shrink):
    """The module docstring's formula in plain numpy, whole clip in memory: each frame's box minus the pixel's
    centred temporal mean, over its temporal spread plus the box's median spread, soft-thresholded at
    ``shrink`` robust deviations, then minus the centred mean of the thresholded frames (windows clamped at
    the clip's ends)."""
    x0, y0, x1, y1 = box
    st = np.array([f[y0:y1, x0:x1] for _, f in frames], np.float64)
    n = len(st)
    lo = [min(max(k - half, 0), n - (2 * half + 1)) for k in range(n)]  # first frame of k's window
    mean = np.array([st[a : a + 2 * half + 1].mean(axis=0) for a in lo])
    sd = np.array([st[a : a + 2 * half + 1].std(axis=0) for a in lo])
    ref = np.median(sd[0])
    z = (st - mean) / (sd + ref)
    for k in range(n):
        tau = shrink * 1.4826 * np.median(np.abs(z[k][::4, ::4]))
        z[k] = np.sign(z[k]) * np.maximum(np.abs(z[k]) - tau, 0)
    zm = np.array([z[a : a + 2 * half + 1].mean(axis=0) for a in lo])
    out = np.zeros((n,) + frames[0][1].shape)
    out[:, y0:y1, x0:x1] = z - zm
    return out


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_the_streaming_standardisation_is_the_formula(dtype):
    """uint8 frames (kept as uint8 in the window) and float32 frames (a filter's output) give the formula's
    frames; the streaming sums, OpenCV's passes and the window's storage change nothing but rounding."""
    from fieldtool.processing import surface

    rng = np.random.default_rng(5)
    base = rng.random((40, 50)) * 150
    frames = [
        (k / 30, np.clip(base + rng.normal(0, 25, base.shape) + 80 * (k % 3 == 0) * (base > 140), 0, 255).astype(dtype))
        for k in range(30)
    ]
    roi = (8, 6, 40, 30)
    got = list(surface.standardize(frames, roi, margin=3, half=5, shrink=surface.SHRINK))
    want = _standardized_by_the_formula(frames, (5, 3, 43, 33), 5, surface.SHRINK)
    assert len(got) == len(want)
    for (t, a), (t0, _), b in zip(got, frames, want, strict=True):
        assert t == t0 and a.dtype == np.float32
        assert np.abs(a - b).max() < 1e-4 * max(np.abs(b).max(), 1.0)
