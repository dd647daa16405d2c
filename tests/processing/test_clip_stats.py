"""The clip's own estimates (processing/clip_stats.py), the gates set from them, and the unmeasured verdict."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from fieldtool.processing import clip_stats as cs


def _clip(n=24, h=128, w=192, level=22.0, amp=8.0, noise=5.0, speed=2.0, density=0.0015, seed=0, glints=0):
    """Gaussian tracers (sigma 2 px, peak ``amp``) drifting ``speed`` px/frame over a flat ``level``, white noise."""
    rng = np.random.default_rng(seed)
    k = int(density * h * w)
    x0, y0 = rng.uniform(0, w, k), rng.uniform(0, h, k)
    yy, xx = np.mgrid[0:h, 0:w]
    out = []
    for i in range(n):
        img = np.full((h, w), level, np.float32)
        for x, y in zip((x0 + speed * i) % w, y0, strict=False):
            img += amp * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 2.0**2))
        if glints:
            gy, gx = rng.integers(0, h, glints), rng.integers(0, w // 4, glints)
            img[gy, gx] += 200.0
        img += noise * rng.standard_normal((h, w))
        out.append(np.clip(img, 0, 255))
    return out


def test_temporal_noise_recovers_the_sd():
    rng = np.random.default_rng(1)
    st = 50 + 3.0 * rng.standard_normal((30, 64, 64))
    assert np.median(cs.temporal_noise(st)) == pytest.approx(3.0, rel=0.1)


def test_noise_ignores_moving_tracers_and_contrast_follows_the_tracers():
    bright = cs.estimate(_clip(amp=60.0, noise=2.0))
    dark = cs.estimate(_clip(amp=8.0, noise=5.0))
    assert bright.noise == pytest.approx(2.0, rel=0.2)
    assert dark.noise == pytest.approx(5.0, rel=0.2)
    assert bright.contrast > 5 * dark.contrast
    assert bright.cnr > cs.CNR_WEAK > dark.cnr


def test_glare_fraction_sees_short_lived_glints():
    assert cs.estimate(_clip(glints=40)).glare_fraction > 5 * max(cs.estimate(_clip()).glare_fraction, 1e-4)


def test_box_and_too_few_frames():
    s = cs.estimate(_clip(), box=(10, 10, 100, 90))
    assert s.windows >= 1 and s.frames == 24
    with pytest.raises(ValueError):
        cs.estimate(_clip(n=2))


def test_soft_threshold_residual():
    assert cs.soft_threshold_residual(0.0) == pytest.approx(1.0)
    r = [cs.soft_threshold_residual(k) for k in (0.5, 1.0, 2.0, 3.0)]
    assert all(a > b for a, b in zip(r, r[1:], strict=False)) and r[-1] < 0.05


def test_gates_keep_the_defaults_on_a_kind_clip_and_lower_them_in_the_dark():
    kind = cs.gates(
        cs.estimate(_clip(amp=60.0, noise=2.0)), shrink_default=3.0, min_texture_default=0.05, min_pairs=2, n_frames=240
    )
    assert (kind.plan, kind.shrink, kind.min_texture, kind.min_pairs) == ("standard", 3.0, 0.05, None)
    dark = cs.gates(
        cs.estimate(_clip(amp=8.0, noise=5.0)), shrink_default=3.0, min_texture_default=0.05, min_pairs=2, n_frames=240
    )
    assert dark.plan == "low_light" and dark.shrink < 3.0 and dark.min_texture <= 0.05 and dark.min_pairs == 239
    assert json.dumps(dark.to_dict())


def test_glare_drops_the_soft_threshold_only_over_faint_tracers():
    """Glints over faint tracers: no soft threshold (it would erase the tracers between the glints). Glints over
    tracers that stand out, sent to the weak path by the self-check: the threshold stays (it removes texture
    fixed in the world, e.g. standing ripples, which would pull the velocities towards zero)."""

    def g(cnr):
        st = cs.ClipStats(
            frames=20, noise=3.0, contrast=3.0 * cnr, cnr=cnr, texture=5.0, level=40.0, glare_fraction=0.05, windows=12
        )
        return cs.gates(st, shrink_default=3.0, min_texture_default=0.05, min_pairs=2, n_frames=240, force="low_light")

    faint, bright = g(4.0), g(9.0)
    assert faint.plan == bright.plan == "low_light+glare" and faint.mask_glints and bright.mask_glints
    assert faint.shrink == 0.0 and faint.min_valid_fraction == 0.0
    assert bright.shrink == 3.0 and bright.min_valid_fraction is None


def test_unmeasured_verdict_is_unusable_with_nan_discharge():
    from fieldtool.processing.cross_section import CrossSection
    from fieldtool.run import unmeasured

    assert unmeasured.nothing_measured(np.full(5, np.nan)) and not unmeasured.nothing_measured(np.array([np.nan, 1.0]))

    class G:  # the section geometry's fields the verdict reads
        station_edges = np.linspace(0.0, 10.0, 6)
        length_m = 10.0

    import fieldtool.processing.discharge as dq

    cs_ = CrossSection(np.array([0.0, 2.0, 8.0, 10.0]), np.array([11.0, 9.0, 9.0, 11.0]))
    orig = dq.subsection_areas
    dq.subsection_areas = lambda g, c, lv: (np.ones(5), np.ones(5))
    try:
        dres, q = unmeasured.verdict(
            G(), cs_, 10.0, 0.85, {"noise": {"temporal_sd_gray": 5.0}, "contrast": {"tracer_gray": 1.0, "cnr": 0.2}}
        )
    finally:
        dq.subsection_areas = orig
    assert np.isnan(dres.discharge_m3s) and dres.velocity_filled.all()
    assert (
        q.grade == "unusable" and q.reasons[0].code == "nothing_measured" and "0.20 x its noise" in q.reasons[0].message
    )


@pytest.mark.slow
def test_dark_clip_is_never_exit_2(tmp_path: Path):
    """A small dusk clip (640x360, 3 s): before issue 23 it stopped with exit 2 ("no valid velocity vector");
    now it is a measurement (exit 0, right or not graded good) or an unusable verdict (exit 3) with result.json."""
    from fieldtool.synthetic import presets, render_scene

    spec = presets.get(
        "low_light",
        seed=0,
        duration_s=3.0,
        camera__width_px=640,
        camera__height_px=360,
        piv_window_px=16,
        piv_overlap_px=8,
    )
    truth = render_scene(spec, tmp_path / "scene")
    out = tmp_path / "res"
    p = subprocess.run(
        [sys.executable, "-m", "fieldtool.cli", "run", str(truth.project_path), "--out", str(out)],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
    )
    assert p.returncode in (0, 3), p.stderr[-500:]
    res = json.loads((out / "result.json").read_text())
    assert res["robust"]["gates"]["plan"] == "low_light"
    assert res["robust"]["noise"]["temporal_sd_gray"] > 2.0
    if p.returncode == 3:
        assert res["quality"]["grade"] == "unusable" and res["quality"]["reasons"]
    if res["discharge_m3s"] is not None:
        err = abs(res["discharge_m3s"] - truth.discharge_m3s) / truth.discharge_m3s
        assert err <= 0.05 or res["quality"]["grade"] != "good"


def test_temporal_mean_lowers_noise_and_keeps_the_displacement():
    from fieldtool.processing.lowlight import temporal_mean

    fr = _clip(n=12, amp=8.0, noise=5.0, speed=2.0, density=0.003)
    out = list(temporal_mean([(i / 30, f) for i, f in enumerate(fr)], half=1))
    assert len(out) == 12 and [t for t, _ in out] == [i / 30 for i in range(12)]
    d_in = np.std(np.diff(np.stack(fr[4:8]), axis=0))
    d_out = np.std(np.diff(np.stack([o for _, o in out[4:8]]), axis=0))
    assert d_out < 0.75 * d_in  # noise down (sqrt(3) for white noise; tracers keep part of the difference)
    skip = list(temporal_mean([(i, f) for i, f in enumerate(fr)], half=1, want=lambda k: k % 2 == 0))
    assert skip[1][1] is None and skip[2][1] is not None
    np.testing.assert_allclose(skip[2][1], out[2][1])
    np.testing.assert_allclose(out[0][1], (fr[0] + fr[1]) / 2, rtol=1e-5)


def test_selfcheck_prefers_the_consistent_variant():
    from fieldtool.processing import selfcheck
    from fieldtool.processing.piv import PivParams

    good = [f - 22.0 for f in _clip(n=10, amp=40.0, noise=1.0, speed=1.5, density=0.003)]
    rng = np.random.default_rng(3)
    bad = [rng.standard_normal(good[0].shape).astype(np.float32) for _ in good]  # no motion: pure noise
    prm = PivParams(window_px=32, overlap_px=16)
    best, scores = selfcheck.choose({"noise": lambda: (bad, prm), "tracers": lambda: (good, prm)}, 1 / 30)
    assert best == "tracers"
    s = {v.name: v for v in scores}
    assert s["tracers"].score > s["noise"].score and s["tracers"].fb < 0.2 and s["tracers"].valid > 0.5


@pytest.mark.slow
def test_blank_clip_ends_unusable_with_every_file(tmp_path: Path):
    """Dark water without a single tracer: nothing can be measured -> exit 3, result.json with a null discharge,
    grade unusable and its reason (exit 2 "no valid velocity vector" before issue 23)."""
    from fieldtool.synthetic import presets, render_scene

    spec = presets.get(
        "low_light",
        seed=0,
        duration_s=2.0,
        particle_brightness=0.0,
        camera__width_px=640,
        camera__height_px=360,
        piv_window_px=16,
        piv_overlap_px=8,
    )
    truth = render_scene(spec, tmp_path / "scene")
    out = tmp_path / "res"
    p = subprocess.run(
        [sys.executable, "-m", "fieldtool.cli", "run", str(truth.project_path), "--out", str(out)],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
    )
    assert p.returncode == 3, p.stderr[-500:]
    res = json.loads((out / "result.json").read_text())
    assert res["discharge_m3s"] is None and res["quality"]["grade"] == "unusable"
    assert res["quality"]["reasons"][0]["code"] == "nothing_measured"
    for f in ("subsections.csv", "mean_field.npz", "vectors.png", "section.png"):
        assert (out / f).exists(), f


def test_glint_background_is_the_median_of_the_frames_where_the_pixel_does_not_shine():
    """clip_stats.background against np.nanmedian of the stack with the bright values taken out; a pixel bright
    in every frame keeps its plain median."""
    rng = np.random.default_rng(3)
    for n in (19, 20):
        stack = (rng.random((n, 40, 30)) * 200).astype(np.float32)
        bright = rng.random(stack.shape) < 0.4
        bright[:, :3, :3] = True  # bright in every frame
        bright[: n - 1, 5, 5], bright[-1, 5, 5] = True, False  # one frame left
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            want = np.nanmedian(np.where(bright, np.nan, stack), axis=0)
        want = np.where(np.isfinite(want), want, np.median(stack, axis=0))
        got = cs.background(stack, bright)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, want, rtol=1e-6)
        assert got[5, 5] == stack[-1, 5, 5]


def test_median0_is_numpys_median_over_the_first_axis():
    rng = np.random.default_rng(4)
    for n in (3, 4, 19, 20):
        stack = (rng.random((n, 17, 23)) * 255).astype(np.float32)
        stack[:, 0, 0] = 7.0  # ties
        got, want = cs.median0(stack), np.median(stack, axis=0)
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_the_self_check_runs_where_either_plan_may_fit():
    """Under half CNR_WEAK: the weak plan; from half to CNR_WEAK: either; above it, the standard gates unless the
    clip has glare (up to twice CNR_WEAK): their looser gates alone would raise the weak plan's valid share."""

    def stats(cnr, glare=0.0):
        return cs.ClipStats(
            frames=20, noise=2.0, contrast=2.0 * cnr, cnr=cnr, texture=5.0, level=80.0, glare_fraction=glare, windows=12
        )

    assert not cs.ambiguous(stats(2.0)) and cs.ambiguous(stats(4.0)) and cs.ambiguous(stats(5.9))
    assert not cs.ambiguous(stats(8.0)) and cs.ambiguous(stats(8.0, glare=2 * cs.GLARE_ON))
    assert not cs.ambiguous(stats(13.0, glare=2 * cs.GLARE_ON))
