"""Robust velocimetry stages: temporal standardisation (glints in place), texture gate, frame gap, first-look
planning, rejection of upstream subsections."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from fieldtool.processing import framepool, piv, planning, robust, surface

FPS = 30.0


def _texture(rng, h, w, density=0.02, sigma=1.2):
    """Particle image: Gaussian blobs (grey levels 0..~120) on 0."""
    img = np.zeros((h, w), np.float32)
    n = int(density * h * w)
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    img[ys, xs] = rng.uniform(600, 1200, n)
    return cv2.GaussianBlur(img, (0, 0), sigma)


def _stream(n, shift_px, rng, glints=0, glint_amp=250.0, h=96, w=256, static_amp=0.0, tracer_gain=1.0):
    """Frames of a texture moving by ``shift_px`` (x) per frame, with static texture and glints that flicker in
    place (independently each frame) over the middle."""
    big = tracer_gain * _texture(rng, h, w + int(np.ceil(shift_px * n)) + 8)
    static = static_amp * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.5)
    gl = np.zeros((glints, h, w), np.float32)
    for k in range(glints):
        y, x = rng.integers(10, h - 10), rng.integers(w // 4, 3 * w // 4)
        gl[k, y - 2 : y + 3, x - 3 : x + 4] = glint_amp
    frames = []
    for i in range(n):
        off = shift_px * i
        m = np.float32([[1, 0, off], [0, 1, 0]])
        img = cv2.warpAffine(big, m, (big.shape[1], h), flags=cv2.INTER_CUBIC)[:, :w] + 40.0 + static
        if glints:
            lit = rng.uniform(size=glints) < 0.35
            img = img + np.tensordot(lit.astype(np.float32), gl, axes=1)
        frames.append((i / FPS, np.clip(img, 0, 255).astype(np.float32)))
    return frames


def _median_dx(res, dt):
    return float(np.nanmedian(res.u * dt))  # warpAffine with +off moves the texture to +x


PARAMS = piv.PivParams(window_px=32, overlap_px=16, passes=1, averaging="ensemble")


def test_standardize_keeps_times_order_and_removes_the_static_pattern():
    rng = np.random.default_rng(1)
    frames = _stream(40, 1.5, rng, static_amp=60.0)
    stats = surface.SurfaceStats()
    out = list(surface.standardize(frames, None, half=5, shrink=0.0, stats=stats))
    assert [t for t, _ in out] == [t for t, _ in frames] and stats.frames == 40
    # a pixel's series over the window has zero mean: what is fixed in the image is gone
    stack = np.array([o for _, o in out[5:16]])
    assert abs(float(stack.mean(axis=0).mean())) < 0.05
    assert np.all(np.isfinite(stack))


def test_blank_frames_are_zeros_and_a_large_one_costs_only_the_pages_written():
    for shape in ((48, 64), (2160, 3840)):
        b = framepool.blank(shape)
        assert b.shape == shape and b.dtype == np.float32 and b.flags.writeable and not b.any()
    with open("/proc/self/statm") as fh:
        before = int(fh.read().split()[1])
    frames = [framepool.blank((2160, 3840)) for _ in range(4)]  # 33 MB each
    for f in frames:
        f[:, 1000:1100] = 1.0  # a narrow box: one 4 KiB page of each row
    with open("/proc/self/statm") as fh:
        grown_mb = (int(fh.read().split()[1]) - before) * 4096 / 2**20
    assert grown_mb < 4 * 14  # the rows' pages only (~8.4 MB a frame), not the whole frames (4 x 33 MB)


def test_standardised_frames_are_read_only_and_recycled_only_when_nothing_refers_to_them():
    """framepool.FramePool: a frame comes back only once no array (the frame or a view of it) is alive; its
    outside stays 0 because nobody can write into a frame handed out."""
    for shape in ((48, 64), (2160, 3840)):
        pool = framepool.FramePool(shape, cap=2)
        box = (10, 20, 30, 40)
        a = pool.filled(box, lambda v: v.fill(1.0))
        with pytest.raises(ValueError):
            a[0, 0] = 5.0  # outside the box: refused, so a recycled frame stays 0 there
        b = pool.filled(box, lambda v: v.fill(2.0))
        assert b is not a
        ida = id(a)
        view = a[20:25]
        del a
        c = pool.filled(box, lambda v: v.fill(3.0))  # a's view lives: not a again (cap 2: a fresh frame)
        assert id(c) != ida and float(view[0, 10]) == 1.0
        del view, c
        d = pool.filled(box, lambda v: v.fill(4.0))
        assert id(d) == ida  # recycled once nothing referred to it
        assert float(d.sum()) == 4.0 * 20 * 20 and not d.flags.writeable


def test_standardize_short_clip_and_empty():
    rng = np.random.default_rng(2)
    frames = _stream(4, 1.0, rng)
    assert len(list(surface.standardize(frames, None, half=15))) == 4
    assert list(surface.standardize([], None)) == []


def test_flickering_glints_in_place_no_longer_pull_piv_to_zero():
    rng = np.random.default_rng(3)
    frames = _stream(60, 2.0, rng, glints=60, glint_amp=250.0, tracer_gain=0.2)  # faint tracers, as at sunset
    raw = piv.analyze(frames, PARAMS)
    std = piv.analyze(list(surface.standardize(frames, None, half=10)), PARAMS)
    dt = 1 / FPS
    assert abs(_median_dx(raw, dt) - 2.0) > 0.5  # the glints win on the raw frames ...
    assert _median_dx(std, dt) == pytest.approx(2.0, abs=0.1)  # ... not once standardised


def test_texture_gate_makes_empty_windows_featureless():
    rng = np.random.default_rng(4)
    frames = _stream(20, 1.0, rng)
    # blank the right half: nothing but a frozen pattern of weak noise (a codec's skipped blocks)
    frozen = rng.normal(0, 1.0, (96, 128)).astype(np.float32)
    frames = [(t, np.concatenate([f[:, :128], 40.0 + frozen], axis=1)) for t, f in frames]
    z = list(surface.standardize(frames, None, half=5))
    res = piv.analyze(
        z, piv.PivParams(window_px=32, overlap_px=16, passes=1, averaging="ensemble", min_texture=surface.MIN_TEXTURE)
    )
    right = res.x > 128 + 16
    assert not res.valid[right & ~res.replaced].any()  # no (zero) vector from the frozen noise
    assert np.isfinite(res.u[~right]).mean() > 0.8


def test_frame_gap_pairs_frames_further_apart():
    rng = np.random.default_rng(5)
    frames = _stream(24, 1.25, rng)
    one = piv.analyze(frames, replace_params(frame_gap=1, averaging="median"))
    three = piv.analyze(frames, replace_params(frame_gap=3, averaging="median"))
    np.testing.assert_allclose(three.dt_s, 3 / FPS, rtol=1e-9)
    assert three.n_pairs == 21 and one.n_pairs == 23
    assert np.nanmedian(three.u) == pytest.approx(np.nanmedian(one.u), rel=0.02)  # px/s, same velocity
    with pytest.raises(Exception, match="piv.frame_gap"):
        piv.analyze(frames[:3], replace_params(frame_gap=3))


def replace_params(**kw):
    from dataclasses import replace

    return replace(PARAMS, **kw)


def test_choose_gap_and_search():
    assert planning.choose(1.35, 2.35, 64) == (2, None)  # slow nodes to >= 2.5 px, fast ones <= 16 px
    assert planning.choose(1.35, 6.0, 64) == (2, None) and planning.choose(1.35, 9.0, 64) == (1, None)
    assert planning.choose(0.5, 1.0, 64) == (planning.MAX_GAP, None)
    gap, search = planning.choose(15.0, 24.0, 64)  # too fast for a 64 px window at one frame
    assert gap == 1 and search is not None and search >= 64 + 2 * 24 and search % 2 == 0
    assert planning.choose(float("nan"), 1.0, 64) == (1, None)


def test_search_side_is_a_fast_fft_size():
    for n in range(64, 400):
        s = planning.fft_side(n)
        assert s >= n and s % 2 == 0
        m = s
        for p in (2, 3):
            while m % p == 0:
                m //= p
        assert m == 1  # only 2 and 3 as prime factors
        # no smaller even side of that kind between n and s
        assert all(not _smooth23(k) for k in range(n + (n % 2), s, 2))
    assert planning.fft_side(124) == 128


def _smooth23(k: int) -> bool:
    for p in (2, 3):
        while k % p == 0:
            k //= p
    return k == 1


def test_first_look_plans_and_replays_every_frame():
    rng = np.random.default_rng(6)
    frames = _stream(30, 1.0, rng)
    plan, replay = planning.first_look(iter(frames), replace_params(passes=2))
    again = list(replay)
    assert len(again) == 30 and all(a[0] == b[0] for a, b in zip(again, frames, strict=True))
    assert plan.fast_px_per_frame == pytest.approx(1.0, abs=0.15)
    assert plan.frame_gap == planning.MAX_GAP and plan.chosen == "auto"  # 1 px per frame: 2.5 px takes 3 frames
    assert json.dumps(plan.as_dict())


def test_a_first_look_at_featureless_first_frames_looks_at_the_next_ones():
    """A clip whose first frames show nothing (a phone's exposure settling from black): the first look finds no
    vectors and looks at the next pairs, which plan as a clip without them does; every frame is still replayed.
    Where holding the frames for another look would pass ``hold_bytes``, it stops at the defaults."""
    rng = np.random.default_rng(6)
    frames = _stream(40, 1.0, rng)
    blank = [(t, np.full_like(img, 40.0)) for t, img in frames[:9]] + frames[9:]
    plain, _ = planning.first_look(iter(frames[9:]), replace_params(passes=2))
    plan, replay = planning.first_look(iter(blank), replace_params(passes=2))
    again = list(replay)
    assert len(again) == 40 and all(a[0] == b[0] for a, b in zip(again, blank, strict=True))
    assert plan.frames_skipped == 9 and plan.frame_gap == plain.frame_gap == planning.MAX_GAP
    assert plan.fast_px_per_frame == pytest.approx(1.0, abs=0.15) and plan.as_dict()["frames_skipped"] == 9
    tight, replay = planning.first_look(iter(blank), replace_params(passes=2), hold_bytes=10 * frames[0][1].nbytes)
    assert tight.frames_skipped == 0 and tight.frame_gap == 1 and len(list(replay)) == 40
    assert math.isnan(tight.fast_px_per_frame) and tight.pairs_looked == 8


def test_reject_upstream():
    v, rej = robust.reject_upstream(np.array([0.1, -0.3, 0.8, 1.0, np.nan, 0.9, 0.02]))
    assert rej.tolist() == [False, True, False, False, False, False, False]
    assert np.isnan(v[1]) and np.isnan(v[4]) and v[6] == 0.02  # slow near a bank is not upstream
    v, rej = robust.reject_upstream(np.array([-0.5, -0.8, -0.2, 0.1]))  # the section goes upstream: left alone
    assert not rej.any()
    assert robust.width_share(np.array([0, 1, 3]), np.array([1, 3, 4]), np.array([True, False, True])) == 0.5


def test_run_reports_robust_facts(short_scene, tmp_path):
    from fieldtool.project.model import load_project
    from fieldtool.run.pipeline import run_project

    proj = load_project(short_scene.project_path)
    res = run_project(proj, tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    r = doc["robust"]
    assert r["plan"]["chosen"] == "auto" and r["plan"]["frame_gap"] >= 1
    assert r["stationary_removed"]["frames"] == short_scene.n_frames
    assert 0.0 <= r["filled_width_share"] <= 1.0 and isinstance(r["upstream_rejected"], list)
    assert res.piv.params.frame_gap == r["plan"]["frame_gap"]
    proj.piv.frame_gap = 1
    proj.piv.remove_stationary = False
    res = run_project(proj, None)
    assert res.robust["plan"]["chosen"] == "user" and "stationary_removed" not in res.robust


def test_zero_peak_removal_leaves_moving_texture_alone_and_blanks_planes():
    from fieldtool.processing import piv_peaks

    rng = np.random.default_rng(7)
    frames = _stream(20, 4.0, rng, h=128, w=256)
    off = piv.analyze(frames, replace_params(passes=2))
    on = piv.analyze(frames, replace_params(passes=2, remove_zero_peak=True))
    inner = np.zeros_like(on.valid)
    inner[1:-1, 1:-1] = True
    assert on.zero_peak_removed[inner].mean() > 0.9 and off.zero_peak_removed is None
    np.testing.assert_allclose(on.u[inner] / FPS, off.u[inner] / FPS, atol=0.02)  # the tracers' peak untouched
    # planes: the block around absolute zero (minus the predictor) is blanked where the node moves only
    corr = rng.random((2, 32, 32)).astype(np.float32)
    before = corr.copy()
    sel = piv_peaks.blank_zero(corr, 0, np.array([0.5, 5.0]), np.array([0.0, 0.0]))
    assert sel.tolist() == [False, True] and np.array_equal(corr[0], before[0])
    block = corr[1][np.ix_([31, 0, 1], [26, 27, 28])]
    assert np.all(block == np.median(before[1]))
    corr[1][np.ix_([31, 0, 1], [26, 27, 28])] = before[1][np.ix_([31, 0, 1], [26, 27, 28])]
    assert np.array_equal(corr[1], before[1])  # nothing else changed


def test_fast_flow_first_pass_starts_from_the_first_look():
    """11 px per frame against a 32 px first-pass window: the look's field becomes the first guess, by which the
    first pass moves its B windows (its search area stays the window); it reads what a wider search reads."""
    rng = np.random.default_rng(8)
    frames = _stream(24, 11.0, rng)
    params = replace_params(passes=2, window_px=16, overlap_px=8)
    plan, replay = planning.first_look(iter(frames), params)
    assert plan.frame_gap == 1 and plan.guess is not None and plan.search_px > 32  # the wider search: the fallback
    assert plan.as_dict()["first_guess"] is True
    xc, yc, dx, dy = plan.guess
    assert dx.shape == (len(yc), len(xc)) and abs(np.median(np.abs(dx)) - 11.0) < 0.5
    res = piv.analyze(replay, params, first_guess=plan.guess)
    ok = res.valid & ~res.replaced
    dt = float(np.median(res.dt_s))
    assert (
        ok.mean() > 0.7 and abs(np.median(np.abs(res.u[ok])) * dt - 11.0) < 0.05
    )  # the upstream edge sees new texture
    assert res.first_guess.shape == res.x.shape + (2,)
    _, search = planning.choose(plan.slow_px_per_frame, plan.fast_px_per_frame, 32)
    wide = piv.analyze(
        iter(frames), replace_params(passes=2, window_px=16, overlap_px=8, search_px=search)
    )  # the other way: a wider search area
    okw = wide.valid & ~wide.replaced
    assert search > 32 and abs(np.median(np.abs(wide.u[okw])) - np.median(np.abs(res.u[ok]))) * dt < 0.05
    with pytest.raises(Exception, match="piv.search_px"):  # the GPU engine cannot move its windows
        piv.analyze(iter(frames), params, backend="gpu", first_guess=plan.guess)


@pytest.mark.parametrize("shift", [14.0, 30.0, 45.0])
def test_flow_beyond_the_first_looks_windows_is_planned_by_the_wide_look(shift):
    """A first look with 32 px windows sees displacements up to 16 px; 14 px is beyond what it trusts
    (GUESS_MAX_FRACTION), 30 and 45 px wrap around its windows (fast water at a low frame rate). The wide look
    (frames reduced by 2, the same windows' footprint searched 2 windows around) reads them, and the first pass
    started from its field reads the flow to 0.05 px."""
    frames = _stream(24, shift, np.random.default_rng(9), w=384)
    params = replace_params(passes=2, window_px=16, overlap_px=8)
    first = planning._look_at(frames[:9], params, None, None, 1, False, wide=False)
    assert first is None or first[1] < planning.GUESS_MIN_VALID or first[0].fast_px_per_frame > 0.4 * 32
    plan, replay = planning.first_look(iter(frames), params)
    assert plan.reduced == 2 and plan.as_dict()["look_reduced"] == 2 and plan.frame_gap == 1
    assert plan.guess is not None and float(np.median(plan.guess[2])) == pytest.approx(shift, abs=0.3)
    assert plan.fast_px_per_frame == pytest.approx(shift, abs=0.3)
    res = piv.analyze(replay, params, first_guess=plan.guess)
    ok = res.valid & ~res.replaced
    assert ok.sum() >= 10 and float(np.median(np.abs(res.u[ok])) * np.median(res.dt_s)) == pytest.approx(
        shift, abs=0.05
    )
    # with a ROI and a mask (both reduced with the frames)
    mask = np.zeros(frames[0][1].shape, bool)
    mask[:10] = True
    boxed, _ = planning.first_look(iter(frames), params, roi=(5, 3, 383, 95), mask=mask)
    assert boxed.reduced == 2 and boxed.fast_px_per_frame == pytest.approx(shift, abs=0.3)
    # frames of noise alone (nothing flows): the wide look's far peaks do not pass the validation, it does not plan
    rng = np.random.default_rng(4)
    noise = [(i / FPS, _texture(rng, 96, 384)) for i in range(24)]
    assert planning._look_at(noise[:9], params, None, None, 1, False, wide=True) is None
    assert planning.first_look(iter(noise), params)[0].reduced == 1
    # within what the first look trusts, it plans alone (the wide look is not asked)
    assert math.isnan(plan.unplanned_fast_px) and plan.as_dict()["wide_look_unplanned_fast_px"] is None
    slow, _ = planning.first_look(iter(_stream(24, 5.0, np.random.default_rng(9))), params)
    assert slow.reduced == 1 and slow.guess is None and slow.fast_px_per_frame == pytest.approx(5.0, abs=0.3)


def test_a_wide_look_with_too_few_vectors_does_not_plan_but_says_how_far_it_saw():
    """70 px a frame across frames 256 px wide: the pattern leaves them within a few frames, and the wide look finds
    a vector at about a tenth of its nodes, too few to plan from. The plan stays the first look's (here: none, the
    defaults), and says how far the wide look saw, for the run's warning (film at a higher frame rate)."""
    frames = _stream(24, 70.0, np.random.default_rng(9), w=256)
    params = replace_params(passes=2, window_px=16, overlap_px=8)
    plan, replay = planning.first_look(iter(frames), params)
    assert plan.reduced == 1 and plan.guess is None and plan.frame_gap == 1 and plan.search_px is None
    assert plan.unplanned_fast_px == pytest.approx(70.0, abs=1.0) and plan.unplanned_valid < planning.WIDE_MIN_VALID
    assert plan.as_dict()["wide_look_unplanned_fast_px"] == pytest.approx(70.0, abs=1.0)
    assert len(list(replay)) == 24


def test_first_look_at_denoised_frames_pairs_them_beyond_the_averaging_window():
    """Frames averaged over 3 share noise with their neighbours: consecutive ones correlate it at zero
    displacement, and a look at them reads a fraction of the 2 px per frame. Looked at 3 frames apart (the
    averaging window) it reads the flow per frame; in the weak-signal plan its ensemble field is the first guess
    (px per frame) whatever the frame gap."""
    from fieldtool.processing import lowlight

    rng = np.random.default_rng(10)
    frames = _stream(16, 2.0, rng, tracer_gain=0.3)
    frames = [(t, f + 20.0 * rng.standard_normal(f.shape).astype(np.float32)) for t, f in frames]
    den = list(lowlight.temporal_mean(frames, 1))
    params = replace_params(passes=2, window_px=16, overlap_px=8)
    near, _ = planning.first_look(iter(den), params)
    assert near.fast_px_per_frame < 0.5  # the shared noise's zero peak
    plan, replay = planning.first_look(iter(den), params, gap=3, weak=True)
    assert plan.fast_px_per_frame == pytest.approx(2.0, abs=0.3) and plan.pairs_looked == planning.LOOK_PAIRS
    assert plan.guess is not None and float(np.median(plan.guess[2])) == pytest.approx(2.0, abs=0.3)
    assert len(list(replay)) == 16
    strong, _ = planning.first_look(iter(den), params, gap=3)  # not weak: no guess where the search suffices
    assert strong.guess is None and strong.search_px is None
