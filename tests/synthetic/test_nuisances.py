"""Synthetic nuisances (synthetic/nuisances.py) and the unseen-scene presets, on small arrays."""

from __future__ import annotations

import numpy as np
import pytest

from fieldtool.synthetic import presets
from fieldtool.synthetic.nuisances import Layer, Nuisances
from fieldtool.synthetic.scene import River


def _layer(nz: Nuisances, seed: int = 0) -> Layer:
    """A top-down canvas: 2 px per 10 cm over X in [-4, 4] m, Y in [-7, 7] m."""
    r = River()
    X, Y = np.meshgrid(np.linspace(-4, 4, 160, dtype=np.float32), np.linspace(7, -7, 280, dtype=np.float32))
    H = np.array([[159 / 8, 0, 79.5], [0, -279 / 14, 139.5], [0, 0, 1.0]])  # world (X, Y) -> canvas px
    sec = np.array([[79.5, 139.5 - 6 * 279 / 14], [79.5, 139.5 + 6 * 279 / 14]])
    return Layer(nz, seed, r, np.stack([X, Y]), H, sec, 30.0, 3.0)


def test_presets_exist_and_vary_the_base_view_with_the_seed():
    cams = set()
    for name in presets.NEW_NAMES:
        for seed in (0, 1, 2):
            s = presets.get(name, seed=seed)
            assert s.name == name and s.duration_s == presets.NEW_DURATION_S and s.seed == seed
            cams.add(s.camera.position_m)
            if name != "drone_4k":
                assert s.nuisances.any
    assert len(cams) >= 3
    low = presets.get("low_light")
    assert (
        round(low.water_gray * 255) == 22
        and 5.5 <= low.particle_brightness * 255 * 0.7 < low.particle_brightness * 255 * 1.3 <= 10.5
    )
    assert presets.get("drone_4k").camera.width_px == 3840
    assert not presets.get("oblique").nuisances.any  # the base scenes draw none


def test_low_light_noise_is_shot_plus_read():
    lay = _layer(presets.get("low_light").nuisances.__class__(read_noise=4.0, shot_gain=0.41))
    img = np.full((280, 160), 22.0, np.float32)
    out = lay.sensor(img.copy(), 0.0, np.random.default_rng(0))
    assert np.std(out - 22.0) == pytest.approx(5.0, rel=0.1)


def test_rain_rings_stay_where_they_fell():
    lay = _layer(Nuisances(rain_rate_m2s=0.5))
    t0, X, Y, _ = lay._rain
    k = int(np.argmin(np.abs(t0 - 1.0)))
    t = t0[k] + 0.3
    a = lay.canvas(np.zeros((280, 160), np.float32), float(t))
    assert a.max() > 0.02
    px = lay._project(np.array([[X[k], Y[k]]]))[0]
    r_px = (0.02 + 0.35 * 0.3) * 159 / 8
    yy, xx = np.mgrid[0:280, 0:160]
    ring = np.abs(np.hypot(xx - px[0], yy - px[1]) - r_px) < 2.0
    assert a[ring].mean() > 3 * a[~ring].mean()  # a ring round the impact point, not carried downstream


def test_exposure_gain_range_and_glitter_only_in_its_column():
    lay = _layer(Nuisances(exposure_amp=0.2))
    g = [lay.gain(t) for t in np.linspace(0, 20, 400)]
    assert 0.8 <= min(g) < 0.95 and 1.05 < max(g) <= 1.25
    lay = _layer(Nuisances(glitter_per_frame=200, glitter_halfwidth_px=10.0))
    a = lay.canvas(np.zeros((280, 160), np.float32), 0.0)
    b = lay.canvas(np.zeros((280, 160), np.float32), 1 / 30)
    cols = np.nonzero(a.max(axis=0) > 0.5)[0]
    assert cols.size and cols.max() - cols.min() <= 2 * 10 + 12
    band = lay._glitter
    assert np.corrcoef(a[band], b[band])[0, 1] < 0.3  # inside the column, each glint lives one frame


def test_debris_moves_with_the_surface_and_shadows_are_fixed():
    lay = _layer(Nuisances(debris=3, shadow_band_depth=0.6))
    base = np.full((280, 160), 0.5, np.float32)
    a = lay.canvas(base.copy(), 0.0)
    b = lay.canvas(base.copy(), 0.5)
    assert not np.allclose(a, b)  # debris moved
    shadow = lay._shadow < 0.9
    assert shadow.any() and np.allclose(a[shadow & (np.abs(a - b) < 1e-6)], b[shadow & (np.abs(a - b) < 1e-6)])
