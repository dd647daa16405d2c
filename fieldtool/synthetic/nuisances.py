"""Nuisances drawn over a synthetic river: low light, rain, shadows, exposure and white balance, debris,
standing waves with a hydraulic jump, and a column of sun glitter under a haze.

Each is a :class:`Nuisances` field (all off by default: a scene without them renders byte for byte as
before) and each draws from a random generator of its own (seeded by the scene's seed), so seeds vary
where they fall. None of them changes the flow: the truth stays the one integrated from the drawn profile.

Three hooks in the render loop (``scene.render_scene``):

- :meth:`Layer.canvas` on the ideal canvas (0..1 brightness, before the lens): things on the water plane
  (shadows, rain rings, debris, standing waves, the jump's roller, glitter, haze) and rain streaks;
- :meth:`Layer.sensor` on the image in grey levels (0..255) before quantisation: exposure pumping,
  vignetting, shot + read noise;
- :meth:`Layer.colour` on the 8-bit BGR frame: white-balance drift.

Units: metres and seconds in the world, pixels on the canvas, grey levels (0..255) on the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np


@dataclass(frozen=True)
class Nuisances:
    """What to draw over the scene (all off by default)."""

    # low light: sensor noise sd = sqrt(read_noise² + shot_gain * signal), both in grey levels
    read_noise: float = 0.0
    shot_gain: float = 0.0
    vignette: float = 0.0  # relative darkening at the image corners (0..1), quadratic in the radius
    # rain: rings born at fixed world points (not advected), plus streaks in the air
    rain_rate_m2s: float = 0.0  # impacts per m² of water per second near the section
    rain_streaks: int = 0  # streaks per frame
    # shadows: a hard band fixed in the world (bridge) plus swaying soft leaf shadows
    shadow_band_depth: float = 0.0  # share of light removed in the band (0..1)
    leaf_shadows: int = 0
    # exposure pumping and white balance
    exposure_amp: float = 0.0  # relative gain amplitude of the 2 s auto-exposure cycle (and its steps)
    white_balance_amp: float = 0.0  # relative drift of the red / blue channel gains
    # large floating debris moving with the surface
    debris: int = 0
    debris_size_m: tuple[float, float] = (0.3, 0.9)
    # standing waves and a hydraulic jump's roller, both fixed in the world
    standing_amp: float = 0.0  # brightness amplitude (0..1) of the standing wave train
    jump_amp: float = 0.0  # brightness of the roller's foam (0..1)
    # glitter column: short-lived glints (one frame each) in a band of the image, under a bright haze
    glitter_per_frame: int = 0
    glitter_halfwidth_px: float = 60.0
    haze: float = 0.0  # share of the image replaced by the haze's brightness (0..1)

    @property
    def any(self) -> bool:
        return any(
            v
            for v in (
                self.read_noise,
                self.shot_gain,
                self.vignette,
                self.rain_rate_m2s,
                self.rain_streaks,
                self.shadow_band_depth,
                self.leaf_shadows,
                self.exposure_amp,
                self.white_balance_amp,
                self.debris,
                self.standing_amp,
                self.jump_amp,
                self.glitter_per_frame,
                self.haze,
            )
        )


def _rng(seed: int, k: int) -> np.random.Generator:
    return np.random.default_rng([seed, 104729, k])


class Layer:
    """The nuisances of one scene, prepared once for its canvas.

    Parameters
    ----------
    nz : what to draw.
    seed : the scene's seed.
    river : the scene's :class:`~fieldtool.synthetic.scene.River` (edges, velocity, level).
    world_xy : (2, h, w) float32 world X, Y (m) of each canvas pixel on the water plane (NaN off the plane).
    H_world : 3x3 world (X, Y) -> canvas pixels.
    section_px : (2, 2) canvas pixels of the section's ends (left, right water edge).
    fps : frames per second.
    roi_half_m : half length (m) of the reach around the section where rain falls and debris floats.
    """

    def __init__(
        self,
        nz: Nuisances,
        seed: int,
        river,
        world_xy: np.ndarray,
        H_world: np.ndarray,
        section_px: np.ndarray,
        fps: float,
        roi_half_m: float,
    ):
        self.nz, self.seed, self.river, self.H = nz, seed, river, H_world
        self.fps = fps
        X, Y = world_xy
        self.h, self.w = X.shape
        self.water = np.isfinite(X) & (Y > river.y_right_edge) & (Y < river.y_left_edge)
        xs = river.x_section_m
        self.L = roi_half_m
        rng = _rng(seed, 0)
        self._shadow = None
        if nz.shadow_band_depth > 0:  # a bridge's shadow: a band ~1.2 m wide, 1.5-3 m from the section
            side = rng.choice([-1.0, 1.0])
            x0 = xs + side * rng.uniform(1.5, 3.0)
            width = rng.uniform(0.9, 1.5)
            tilt = np.tan(np.radians(rng.uniform(-15, 15)))
            d = np.abs(np.where(np.isfinite(X), X - x0 - tilt * Y, 1e9)) - width / 2
            soft = np.clip(0.5 - d / 0.06, 0, 1)  # a 6 cm penumbra
            self._shadow = (1.0 - nz.shadow_band_depth * soft).astype(np.float32)
        self._leaves: tuple[Any, ...] | None = None  # drawn parameters, None when off
        if nz.leaf_shadows > 0:  # blobs over the near bank's water, swaying in the wind
            n = nz.leaf_shadows
            cx = xs + rng.uniform(-roi_half_m, roi_half_m, n)
            cy = river.y_left_edge - rng.uniform(0.0, 0.4, n) * river.width_m
            r = rng.uniform(0.15, 0.5, n)
            f = rng.uniform(0.3, 1.2, n)
            ph = rng.uniform(0, 2 * np.pi, n)
            amp = rng.uniform(0.05, 0.3, n)
            self._leaves = (cx, cy, r, f, ph, amp)
            self._small = (max(self.w // 4, 1), max(self.h // 4, 1))
            self._Xs = cv2.resize(np.nan_to_num(X, nan=1e6), self._small, interpolation=cv2.INTER_AREA)
            self._Ys = cv2.resize(np.nan_to_num(Y, nan=1e6), self._small, interpolation=cv2.INTER_AREA)
        self._rain: tuple[Any, ...] | None = None  # drawn parameters, None when off
        if nz.rain_rate_m2s > 0:  # impacts: (t0, X, Y) over the reach, rings spreading at 0.35 m/s for 0.7 s
            area = 2 * roi_half_m * river.width_m
            dur = 60.0
            n = rng.poisson(nz.rain_rate_m2s * area * dur)
            self._rain = (
                rng.uniform(-1.0, dur, n),
                xs + rng.uniform(-roi_half_m, roi_half_m, n),
                rng.uniform(river.y_right_edge + 0.1, river.y_left_edge - 0.1, n),
                rng.uniform(0.5, 1.0, n),
            )
        self._debris: tuple[Any, ...] | None = None  # drawn parameters, None when off
        if nz.debris > 0:  # rigid polygons (X, Y offsets, m) whose centre moves at the surface velocity
            n = nz.debris
            y = rng.uniform(river.y_right_edge + 0.6, river.y_left_edge - 0.6, n)
            x0 = xs + rng.uniform(-3 * roi_half_m, roi_half_m, n)
            shapes = []
            for _ in range(n):
                k = int(rng.integers(5, 9))
                ang = np.sort(rng.uniform(0, 2 * np.pi, k))
                rad = rng.uniform(*nz.debris_size_m) / 2 * rng.uniform(0.5, 1.0, k)
                stretch = rng.uniform(1.0, 2.5)
                shapes.append(np.column_stack([stretch * rad * np.cos(ang), rad * np.sin(ang)]))
            self._debris = (x0, y, river.surface_velocity_y(y), shapes, rng.uniform(0.05, 0.45, n))
        self._standing = None
        if nz.standing_amp > 0 or nz.jump_amp > 0:
            lam = rng.uniform(0.4, 1.0)
            xw = xs + rng.uniform(-roi_half_m, -0.5)  # the wave train upstream of the jump
            s0 = rng.uniform(0.1, 0.4)
            band = (Y < river.y_left_edge - s0 * river.width_m) & (Y > river.y_left_edge - (s0 + 0.5) * river.width_m)
            env = np.exp(-0.5 * ((np.nan_to_num(X, nan=1e6) - xw) / 1.0) ** 2) * band * self.water
            wave = nz.standing_amp * env * np.sin(2 * np.pi * np.nan_to_num(X) / lam)
            xj = xs + rng.uniform(0.8, 0.6 * roi_half_m + 0.8)
            jump = (np.abs(np.nan_to_num(X, nan=1e6) - xj) < 0.35) & band & self.water
            rows, cols = np.nonzero(jump)
            box = (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1) if rows.size else None
            self._standing = (wave.astype(np.float32), jump, box)
        self._glitter = None
        if nz.glitter_per_frame > 0 or nz.haze > 0:  # an image column through the middle of the section
            mid = section_px.mean(axis=0) + (section_px[1] - section_px[0]) * rng.uniform(-0.1, 0.1)
            xc = mid[0]
            cols = np.arange(self.w)
            col = np.abs(cols - xc) < nz.glitter_halfwidth_px
            self._glitter = col[None, :] & self.water
            hz = np.exp(-0.5 * ((cols - xc) / (3 * nz.glitter_halfwidth_px)) ** 2).astype(np.float32)
            self._haze = np.broadcast_to(nz.haze * (0.5 + 0.5 * hz)[None, :], (self.h, self.w)).astype(np.float32)
            ys, xs_ = np.nonzero(self._glitter)
            self._glitter_px = (ys, xs_)
        self._frng = _rng(seed, 1)  # per-frame draws (glitter, foam, streaks)
        self._expo = None
        if nz.exposure_amp > 0:  # a 2 s cycle plus random steps every few seconds
            t_steps = np.cumsum(rng.uniform(1.5, 3.5, 40))
            jumps = rng.uniform(-1, 1, 40) * nz.exposure_amp * 0.6
            self._expo = (rng.uniform(0, 2 * np.pi), t_steps, jumps)
        self._wb = (rng.uniform(0, 2 * np.pi, 2), rng.uniform(0.1, 0.3, 2))
        self._vig = None
        if nz.vignette > 0:
            yy, xx = np.mgrid[0 : self.h, 0 : self.w].astype(np.float32)
            r2 = ((xx - (self.w - 1) / 2) ** 2 + (yy - (self.h - 1) / 2) ** 2) / (
                ((self.w - 1) / 2) ** 2 + ((self.h - 1) / 2) ** 2
            )
            self._vig = (1.0 - nz.vignette * r2).astype(np.float32)

    # -- the canvas (0..1), before the lens ----------------------------------------------------------
    def canvas(self, img: np.ndarray, t: float) -> np.ndarray:
        nz = self.nz
        if self._standing is not None:
            wave, jump, box = self._standing
            img += wave
            if box is not None and nz.jump_amp > 0:  # turbulent foam, redrawn each frame (not advected)
                r0, r1, c0, c1 = box
                foam = cv2.GaussianBlur(self._frng.standard_normal((r1 - r0, c1 - c0)).astype(np.float32), (0, 0), 2.0)
                foam = nz.jump_amp * (0.6 + 2.0 * foam)
                img[r0:r1, c0:c1] += np.where(jump[r0:r1, c0:c1], foam, 0.0)
        if self._rain is not None:
            self._draw_rain(img, t)
        if self._debris is not None:
            self._draw_debris(img, t)
        if self._shadow is not None:
            img *= self._shadow
        if self._leaves is not None:
            img *= self._leaf_factor(t)
        if self._glitter is not None:
            if nz.haze > 0:
                img *= 1.0 - self._haze
                img += self._haze * 0.85
            if nz.glitter_per_frame > 0:
                ys, xs = self._glitter_px
                k = self._frng.integers(0, ys.size, nz.glitter_per_frame)
                imp = np.zeros_like(img)
                sx, sy = 2.2, 1.0
                np.add.at(imp, (ys[k], xs[k]), self._frng.uniform(1.0, 2.5, k.size) * 2 * np.pi * sx * sy)
                img += cv2.GaussianBlur(imp, (0, 0), sigmaX=sx, sigmaY=sy)
        if nz.rain_streaks > 0:
            streak = np.zeros_like(img)
            n = nz.rain_streaks
            p0 = self._frng.uniform([0, 0], [self.w, self.h], (n, 2))
            ang = np.radians(self._frng.normal(100, 5, n))
            ln = self._frng.uniform(15, 45, n)
            p1 = p0 + ln[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
            for a, b, v in zip(p0.astype(int), p1.astype(int), self._frng.uniform(0.04, 0.12, n), strict=False):
                cv2.line(streak, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), float(v), 1)
            img += cv2.GaussianBlur(streak, (0, 0), 0.8)
        return img

    def _leaf_factor(self, t: float) -> np.ndarray:
        assert self._leaves is not None  # called only when leaves are on
        cx, cy, r, f, ph, amp = self._leaves
        acc = np.zeros(self._Xs.shape, np.float32)
        sway = amp * np.sin(2 * np.pi * f * t + ph)
        for j in range(len(cx)):
            d2 = ((self._Xs - cx[j] - sway[j]) ** 2 + (self._Ys - cy[j] - 0.5 * sway[j]) ** 2) / r[j] ** 2
            acc = np.maximum(acc, np.exp(-0.5 * d2**2))
        fac = 1.0 - 0.45 * acc
        return cv2.resize(fac, (self.w, self.h), interpolation=cv2.INTER_LINEAR)

    def _project(self, xy: np.ndarray) -> np.ndarray:
        p = np.column_stack([xy, np.ones(len(xy))]) @ self.H.T
        return p[:, :2] / p[:, 2:3]

    def _draw_rain(self, img: np.ndarray, t: float) -> None:
        assert self._rain is not None  # called only when rain is on
        t0, X, Y, a = self._rain
        age = t - t0
        live = (age > 0) & (age < 0.7)
        if not live.any():
            return
        ring = np.zeros_like(img)
        ang = np.linspace(0, 2 * np.pi, 33)
        for x, y, ag, amp in zip(X[live], Y[live], age[live], a[live], strict=False):
            r = 0.02 + 0.35 * ag
            pts = self._project(np.column_stack([x + r * np.cos(ang), y + r * np.sin(ang)]))
            v = 0.18 * amp * (1.0 - ag / 0.7)
            cv2.polylines(ring, [np.round(pts * 16).astype(np.int32)], True, float(v), 2, cv2.LINE_8, 4)
        img += cv2.GaussianBlur(ring, (0, 0), 0.8)

    def _draw_debris(self, img: np.ndarray, t: float) -> None:
        assert self._debris is not None  # called only when debris is on
        x0, y, u, shapes, val = self._debris
        span = 4 * self.L
        xs = self.river.x_section_m
        h, w = img.shape
        for j in range(len(x0)):
            xc = xs - 3 * self.L + np.mod(x0[j] - (xs - 3 * self.L) + u[j] * t, span)
            pts = self._project(shapes[j] + [xc, y[j]])
            if not np.all(np.isfinite(pts)):
                continue
            c0, r0 = np.maximum(np.floor(pts.min(axis=0)).astype(int) - 4, 0)
            c1, r1 = np.minimum(np.ceil(pts.max(axis=0)).astype(int) + 5, [w, h])
            if c1 <= c0 or r1 <= r0:
                continue
            mask = np.zeros((r1 - r0, c1 - c0), np.uint8)  # the object's box only
            cv2.fillPoly(mask, [np.round((pts - [c0, r0]) * 16).astype(np.int32)], 255, cv2.LINE_AA, 4)
            m = cv2.GaussianBlur(mask, (0, 0), 0.7).astype(np.float32) / 255.0
            sub = img[r0:r1, c0:c1]
            sub *= 1.0 - m
            sub += m * val[j]

    # -- the sensor (grey levels) ----------------------------------------------------------------
    def gain(self, t: float) -> float:
        if self._expo is None:
            return 1.0
        ph, ts, jumps = self._expo
        g = 1.0 + self.nz.exposure_amp * 0.6 * np.sin(2 * np.pi * t / 2.0 + ph)
        k = int(np.searchsorted(ts, t))
        g += jumps[k - 1] if k > 0 else 0.0  # the last step's offset (steps do not accumulate)
        return float(np.clip(g, 1.0 - self.nz.exposure_amp, 1.0 + 1.25 * self.nz.exposure_amp))

    def sensor(self, img: np.ndarray, t: float, rng: np.random.Generator) -> np.ndarray:
        """``img`` in grey levels (h, w) after the lens: exposure, vignetting, shot + read noise."""
        nz = self.nz
        g = self.gain(t)
        if g != 1.0:
            img *= g
        if self._vig is not None and self._vig.shape == img.shape:
            img *= self._vig
        if nz.read_noise > 0 or nz.shot_gain > 0:
            sd = np.sqrt(nz.read_noise**2 + nz.shot_gain * np.maximum(img, 0.0))
            img += sd * rng.standard_normal(img.shape, dtype=np.float32)
        return img

    def colour(self, bgr: np.ndarray, t: float) -> np.ndarray:
        """White-balance drift of the 8-bit BGR frame (red and blue gains wander over ~10 s)."""
        if self.nz.white_balance_amp <= 0:
            return bgr
        ph, fr = self._wb
        a = self.nz.white_balance_amp
        gr = 1.0 + a * np.sin(2 * np.pi * fr[0] * t + ph[0])
        gb = 1.0 - a * np.sin(2 * np.pi * fr[1] * t + ph[1])
        out = bgr.astype(np.float32)
        out[..., 0] *= gb
        out[..., 2] *= gr
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)
