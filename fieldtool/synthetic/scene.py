"""Synthetic seeded river with a KNOWN discharge, rendered as a video with its project file.

World: right-handed X, Y, Z (metres), Z up; flow along +X; the water surface is the plane
Z = ``River.level_m`` (the cross-section datum). Looking downstream the left bank is at larger Y;
station s runs from the left bank top to the right bank top, ``Y = y_left_top - s``; the surveyed
section lies at X = ``River.x_section_m``. Everything, banks included, is drawn in the plane
Z = level, so a plane homography maps it exactly to the (undistorted) image.

Bed: d(s) = depth_m * f(u), u = (s - s_left) / width_m, f(u) = u^a (1-u)^b / max (a = b = 0 is a
rectangular channel). Surface velocity along +X: u_s(s) = u_max_ms * (d(s) / depth_m)^(2/3).
True discharge Q = alpha * integral(u_s * d ds), by ``scipy.integrate.quad`` on those functions,
independent of any pipeline code.

Frames: particles on the water advected exactly by u_s(Y) * t (periodic in X), splatted into a
world-space raster, blurred to their diameter, warped to the image with the exact homography,
optionally distorted (remap), shaken, glinted, with sensor noise. Frame i is at t = i / fps.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy import integrate

from fieldtool.errors import Cancelled, ParameterError
from fieldtool.processing.cross_section import CrossSection, to_csv_text
from fieldtool.project.model import (
    CalibrationCfg,
    CrossSectionCfg,
    OrthoCfg,
    PivCfg,
    Project,
    RoiCfg,
    SectionCfg,
    StabilizeCfg,
    VideoCfg,
    WaterLevelCfg,
    atomic_write_bytes,
    save_project,
)
from fieldtool.synthetic.camera import Camera, render_canvas
from fieldtool.synthetic.checkerboard import render_checkerboard
from fieldtool.synthetic.mkv import TIMECODE_SCALE_NS, MkvWriter, ticks_of
from fieldtool.synthetic.nuisances import Layer, Nuisances


@dataclass(frozen=True)
class River:
    """Geometry and flow of a synthetic river (metres, m/s)."""

    width_m: float = 12.0  # wetted width at the level
    depth_m: float = 1.5  # deepest point below the level
    shape_a: float = 1.2  # exponent at the left water edge
    shape_b: float = 0.7  # exponent at the right water edge (smaller = steeper bank)
    u_max_ms: float = 1.2  # surface velocity at the deepest point
    alpha: float = 0.85  # velocity index: depth-averaged / surface velocity
    level_m: float = 10.0  # water level in the cross-section datum
    left_bank_m: float = 5.0  # plan width of the dry left bank (edge -> bank top)
    right_bank_m: float = 5.0
    left_bank_height_m: float = 0.6  # bank top above the level
    right_bank_height_m: float = 0.8
    x_section_m: float = 0.0  # X of the surveyed section
    island_m: tuple[float, float] | None = (
        None  # (from, to) distance from the left water edge (m): a bar 0.15 m above the level
    )

    # -- geometry ---------------------------------------------------------------------------
    @property
    def s_left(self) -> float:
        """Station of the left water edge (m)."""
        return self.left_bank_m

    @property
    def s_right(self) -> float:
        """Station of the right water edge (m)."""
        return self.left_bank_m + self.width_m

    @property
    def s_total(self) -> float:
        """Station of the right bank top (m)."""
        return self.s_right + self.right_bank_m

    @property
    def y_left_top(self) -> float:
        """World Y of station 0 (m)."""
        return self.s_left + self.width_m / 2.0

    @property
    def y_left_edge(self) -> float:
        return self.width_m / 2.0

    @property
    def y_right_edge(self) -> float:
        return -self.width_m / 2.0

    def station_of_y(self, y: np.ndarray | float) -> np.ndarray | float:
        return self.y_left_top - y

    def y_of_station(self, s: np.ndarray | float) -> np.ndarray | float:
        return self.y_left_top - s

    def _fmax(self) -> float:
        a, b = self.shape_a, self.shape_b
        if a == 0 and b == 0:
            return 1.0
        u = a / (a + b)
        return u**a * (1 - u) ** b

    def depth(self, s: np.ndarray | float) -> np.ndarray:
        """Water depth (m) at station s; 0 outside the water."""
        s = np.asarray(s, float)
        u = (s - self.s_left) / self.width_m
        inside = (u > 0) & (u < 1)
        uc = np.clip(u, 1e-300, 1 - 1e-16)
        f = uc**self.shape_a * (1 - uc) ** self.shape_b / self._fmax()
        return np.where(inside & ~self.on_island(s), self.depth_m * f, 0.0)

    def on_island(self, s: np.ndarray | float) -> np.ndarray:
        """True at stations (m) on the island (dry bar inside the river), if any."""
        s = np.asarray(s, float)
        if self.island_m is None:
            return np.zeros(s.shape, bool)
        a, b = self.island_m
        return (s > self.s_left + a) & (s < self.s_left + b)

    def surface_velocity(self, s: np.ndarray | float) -> np.ndarray:
        """Surface velocity along +X (m/s) at station s."""
        return self.u_max_ms * (self.depth(s) / self.depth_m) ** (2.0 / 3.0)

    def surface_velocity_y(self, y: np.ndarray) -> np.ndarray:
        """Surface velocity along +X (m/s) at world Y."""
        return self.surface_velocity(self.station_of_y(y))

    def bed_elevation(self, s: np.ndarray | float) -> np.ndarray:
        """Bed elevation (m, datum of the level): the channel in the water, straight banks outside."""
        s = np.asarray(s, float)
        z = self.level_m - self.depth(s)
        left = s <= self.s_left
        right = s >= self.s_right
        z = np.where(left, self.level_m + self.left_bank_height_m * (self.s_left - s) / self.left_bank_m, z)
        z = np.where(right, self.level_m + self.right_bank_height_m * (s - self.s_right) / self.right_bank_m, z)
        return np.where(self.on_island(s), self.level_m + 0.15, z)

    def survey(self, spacing_m: float = 0.25) -> CrossSection:
        """Surveyed points of the bed every ``spacing_m`` (m), the water edges included."""
        n = int(np.ceil(self.s_total / spacing_m))
        s = np.linspace(0.0, self.s_total, n + 1)
        s = np.unique(np.concatenate([s, [self.s_left, self.s_right]]))
        if self.shape_a == 0 or self.shape_b == 0:  # vertical wall: a point just inside the water
            eps = 1e-4
            s = np.unique(np.concatenate([s, [self.s_left + eps, self.s_right - eps]]))
        if self.island_m is not None:  # the island's vertical sides: a point on each side of each
            a, b = self.s_left + self.island_m[0], self.s_left + self.island_m[1]
            s = np.unique(np.concatenate([s, [a, a + 1e-4, b - 1e-4, b]]))
        return CrossSection(s, self.bed_elevation(s))

    # -- truth --------------------------------------------------------------------------------
    def truth(self) -> dict:
        """True discharge (m³/s), wetted width (m), area (m²) and mean velocity (m/s), integrated
        with ``scipy.integrate.quad`` on the analytic functions."""
        lo, hi = self.s_left, self.s_right
        opts: dict[str, Any] = dict(limit=200, epsabs=1e-12, epsrel=1e-10)
        if self.island_m is not None:  # the island's sides are discontinuities of the integrands
            opts["points"] = [self.s_left + self.island_m[0], self.s_left + self.island_m[1]]
        area, _ = integrate.quad(lambda s: float(self.depth(s)), lo, hi, **opts)
        q_surf, _ = integrate.quad(lambda s: float(self.surface_velocity(s) * self.depth(s)), lo, hi, **opts)
        q = self.alpha * q_surf
        return {
            "discharge_m3s": q,
            "wetted_width_m": self.width_m - (self.island_m[1] - self.island_m[0] if self.island_m else 0.0),
            "wetted_area_m2": area,
            "mean_velocity_ms": q / area,
            "surface_discharge_m3s": q_surf,
            "water_level_m": self.level_m,
            "alpha": self.alpha,
        }


# ---------------------------------------------------------------------------------------------
# scene description


@dataclass(frozen=True)
class SceneSpec:
    """Everything that defines a synthetic scene; the same spec and seed give the same video.

    Lengths in metres, intensities on a 0..1 scale (noise in 8-bit grey levels), angles in degrees.
    """

    name: str
    river: River
    camera: Camera
    seed: int = 0
    fps: float = 30.0
    duration_s: float = 5.0
    # tracers
    particle_density_m2: float = 25.0  # particles per m² of water surface
    particle_diameters_m: tuple[float, ...] = (0.06,)  # one class per diameter, equal shares
    particle_brightness: float = 0.7  # peak brightness above the water (0..1), varied +-30 %
    texture_res_m: float = 0.015  # world raster pixel size (m)
    max_extent_m: float = 40.0  # the raster covers the visible plane, at most this far from the section
    # appearance
    water_gray: float = 0.18
    bank_gray: float = 0.55
    bank_contrast: float = 0.18
    noise_sigma: float = 2.0  # sensor noise, grey levels (0..255)
    # variants
    shake_px: float = 0.0  # sd of the random image translation per frame (px); frame 0 unshaken
    shake_deg: float = 0.0  # sd of the random image rotation per frame (deg)
    shake_drift_px_s: float = 0.0  # slow drift of the view (px/s), as a hovering drone or a tired hand
    glints: int = 0  # number of static sun glints on the water (fixed in the image, flickering)
    checkerboard_frames: int = 40  # distorted cameras: frames of the calibration video
    checkerboard_square_m: float = 0.05
    # what the hydrologist enters
    gcp_offset_m: float = 0.8  # GCPs this far beyond the water edges, on the banks
    gcp_half_dx_m: float = 4.0  # GCPs at x_section +- this
    gcp_size_m: float = 0.4  # side of the checker target
    extra_gcps: int = 0  # more targets on the banks beyond P1..P4, spread over the image (pose, lens fit)
    click_error_px: float = 0.3  # sd of the seeded click error on GCP pixels
    survey_spacing_m: float = 0.25
    roi_half_length_m: float = 3.0  # ROI covers the water within x_section +- this
    n_sub: int = 15
    piv_window_px: int = 32
    piv_overlap_px: int = 16
    video_name: str = "river.mp4"
    fourcc: str = "mp4v"
    # hard-scene variants (all off by default, so the base scenes render byte for byte as before;
    # their random draws come from generators of their own, never from the base one)
    patch_cover: float = 0.0  # > 0: seeding kept only in patches covering this share of the water
    patch_scale_m: float = 1.5  # size of the seeding patches (m)
    empty_band_m: tuple[float, float] = (0.0, 0.0)  # band of stations (m from the left water edge) that empties
    empty_after_s: float = 0.0  # ... at this time (s), fading out over 0.2 s
    section_glints: int = 0  # sun glints flickering in place on part of the section
    section_glint_span: tuple[float, float] = (0.25, 0.75)  # ... between these fractions of the width
    section_glint_half_m: float = 1.2  # ... within this distance (m) up/downstream of the section
    glint_duty: float = 0.35  # probability that a glint group is lit in a frame
    ripple_amp: float = 0.0  # wind ripples: brightness amplitude (0..1) of the slope pattern
    ripple_dir_deg: float = 160.0  # mean direction they travel, from +X (flow) towards +Y (left bank)
    ripple_spread_deg: float = 40.0  # directional spread (+-)
    ripple_lambda_m: tuple[float, float] = (0.08, 0.5)  # wavelength range (m)
    ripple_waves: int = 12  # number of wave components
    section_skew_deg: float = 0.0  # surveyed section at this angle to the channel's normal (flow stays along +X)
    jpeg_quality: int = 0  # 1..100: each frame goes through JPEG at this quality before the video codec
    drop_fraction: float = 0.0  # > 0: variable-frame-rate Matroska (MJPEG) with this share of frames dropped
    nuisances: Nuisances = field(default_factory=Nuisances)  # low light, rain, shadows, ... (synthetic/nuisances.py)

    @property
    def n_frames(self) -> int:
        return int(round(self.duration_s * self.fps))

    def with_(self, **changes) -> SceneSpec:
        """A copy with fields replaced; ``river__x`` / ``camera__x`` change a field of those parts."""
        river = {k[7:]: v for k, v in changes.items() if k.startswith("river__")}
        cam = {k[8:]: v for k, v in changes.items() if k.startswith("camera__")}
        nzc = {k[11:]: v for k, v in changes.items() if k.startswith("nuisances__")}
        own = {k: v for k, v in changes.items() if "__" not in k}
        if nzc:
            own["nuisances"] = replace(self.nuisances, **nzc)
        if river:
            own["river"] = replace(self.river, **river)
        if cam:
            own["camera"] = replace(self.camera, **cam)
        return replace(self, **own)


@dataclass
class SceneTruth:
    """What was rendered and the truth the pipeline must find (also written as truth.json)."""

    discharge_m3s: float
    water_level_m: float
    alpha: float
    wetted_width_m: float
    wetted_area_m2: float
    mean_velocity_ms: float
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist: np.ndarray
    gcp_world_m: np.ndarray  # (4 + extra_gcps, 3) P1..P4 then the extra targets
    gcp_px: np.ndarray  # (4 + extra_gcps, 2) exact projections (frame 0)
    section_px: np.ndarray  # (2, 2) left, right water edge at x_section (frame 0)
    video_path: Path
    project_path: Path
    cross_section_path: Path
    truth_path: Path
    n_frames: int
    fps: float
    seconds_per_frame: float
    section_motion_px: list[float]  # image displacement per frame at 10 %, 50 %, 90 % of the width
    checkerboard_path: Path | None = None
    spec: SceneSpec | None = field(default=None, repr=False)


# ---------------------------------------------------------------------------------------------
# geometry helpers


def gcp_world(spec: SceneSpec) -> np.ndarray:
    """World points (4, 3) of the GCP targets, P1, P2 on the left bank (upstream, downstream),
    P3, P4 on the right bank (downstream, upstream): going round the quadrilateral."""
    r = spec.river
    xs, dx = r.x_section_m, spec.gcp_half_dx_m
    yl = r.y_left_edge + spec.gcp_offset_m
    yr = r.y_right_edge - spec.gcp_offset_m
    base = np.array(
        [[xs - dx, yl, r.level_m], [xs + dx, yl, r.level_m], [xs + dx, yr, r.level_m], [xs - dx, yr, r.level_m]]
    )
    if spec.extra_gcps <= 0:
        return base
    # candidates on both banks, kept where they are seen well inside the frame; the farthest from those
    # already chosen (in the image) first, so the extra targets reach towards the corners
    cam = spec.camera
    cx = xs + dx * np.linspace(-4.0, 4.0, 17)
    cand = np.array(
        [[x, y, r.level_m] for x in cx for y in (yl + 0.5, yl + 2.0, yl + 3.5, yr - 0.5, yr - 2.0, yr - 3.5)]
    )
    depth = (cam.R @ cand.T + cam.t.reshape(3, 1))[2]
    px = cam.project(cand)
    m = 40.0
    ok = (depth > 0) & (px[:, 0] > m) & (px[:, 0] < cam.width_px - m) & (px[:, 1] > m) & (px[:, 1] < cam.height_px - m)
    cand, px = cand[ok], px[ok]
    chosen, chosen_px = list(base), list(cam.project(base))
    for _ in range(min(spec.extra_gcps, len(cand))):
        d = np.min(np.linalg.norm(px[:, None, :] - np.asarray(chosen_px)[None], axis=2), axis=1)
        k = int(np.argmax(d))
        chosen.append(cand[k])
        chosen_px.append(px[k])
        px[k] = np.asarray(chosen_px)[0]  # never again
    return np.asarray(chosen)


def gcp_distances(p: np.ndarray) -> list[float]:
    """L1..L6 = |P1P2|, |P2P3|, |P3P4|, |P4P1|, |P1P3|, |P2P4| (m)."""
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2), (1, 3)]
    return [float(np.linalg.norm(p[i] - p[j])) for i, j in pairs]


def _world_of_pixels(cam: Camera, level: float, px_ideal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane points (N, 2) hit by the rays of ideal pixels, and a mask of rays that hit in front."""
    Kinv = np.linalg.inv(cam.K)
    rays = (cam.R.T @ (Kinv @ np.column_stack([px_ideal, np.ones(len(px_ideal))]).T)).T
    c = np.asarray(cam.position_m, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (level - c[2]) / rays[:, 2]
    ok = np.isfinite(lam) & (lam > 0)
    pts = c[:2] + rays[:, :2] * np.where(ok, lam, 0.0)[:, None]
    return pts, ok


@dataclass(frozen=True)
class _Raster:
    x0: float  # world X of texel column 0 (m)
    y_top: float  # world Y of texel row 0 (m); rows go towards -Y
    res: float
    nx: int
    ny: int

    @property
    def to_world(self) -> np.ndarray:
        """3x3: texel (col, row, 1) -> world (X, Y, 1)."""
        return np.array([[self.res, 0.0, self.x0], [0.0, -self.res, self.y_top], [0.0, 0.0, 1.0]])

    def xy(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x0 + np.arange(self.nx) * self.res, self.y_top - np.arange(self.ny) * self.res


def _raster_for_view(spec: SceneSpec, canvas_offset: tuple[int, int], canvas_size: tuple[int, int]) -> _Raster:
    """World raster covering what the (enlarged) canvas sees of the plane, clipped to the extent."""
    cam, r = spec.camera, spec.river
    cw, ch = canvas_size
    gx, gy = np.meshgrid(np.linspace(0, cw - 1, 97), np.linspace(0, ch - 1, 55))
    ideal = np.column_stack([gx.ravel() - canvas_offset[0], gy.ravel() - canvas_offset[1]])
    pts, ok = _world_of_pixels(cam, r.level_m, ideal)
    if not ok.any():
        raise ParameterError(f"scene {spec.name}: the camera does not see the water plane")
    ext = spec.max_extent_m
    lim_x = (r.x_section_m - ext, r.x_section_m + ext)
    lim_y = (-ext, ext)
    far = np.where(ok[:, None], pts, np.nan)
    # rays above the horizon: the view reaches the extent limit in their direction
    xmin, xmax = np.nanmin(far[:, 0]), np.nanmax(far[:, 0])
    ymin, ymax = np.nanmin(far[:, 1]), np.nanmax(far[:, 1])
    if not ok.all():
        xmin, xmax, ymin, ymax = lim_x[0], lim_x[1], lim_y[0], lim_y[1]
    pad = 1.0
    xmin, xmax = max(xmin - pad, lim_x[0]), min(xmax + pad, lim_x[1])
    ymin, ymax = max(ymin - pad, lim_y[0]), min(ymax + pad, lim_y[1])
    # the water near the section must be inside the raster
    xmin = min(xmin, r.x_section_m - spec.gcp_half_dx_m - 1)
    xmax = max(xmax, r.x_section_m + spec.gcp_half_dx_m + 1)
    ymin = min(ymin, r.y_right_edge - spec.gcp_offset_m - 1)
    ymax = max(ymax, r.y_left_edge + spec.gcp_offset_m + 1)
    res = max(spec.texture_res_m, np.sqrt((xmax - xmin) * (ymax - ymin) / 16e6))
    nx = int(np.ceil((xmax - xmin) / res)) + 1
    ny = int(np.ceil((ymax - ymin) / res)) + 1
    return _Raster(float(xmin), float(ymax), float(res), nx, ny)


def _multiscale_noise(rng: np.random.Generator, ny: int, nx: int, scales_px: tuple[float, ...]) -> np.ndarray:
    """Static texture with features at several scales, zero mean, unit sd (float32)."""
    out = np.zeros((ny, nx), np.float32)
    for s in scales_px:
        sy, sx = max(int(ny / s), 2), max(int(nx / s), 2)
        n = rng.standard_normal((sy, sx)).astype(np.float32)
        out += cv2.resize(n, (nx, ny), interpolation=cv2.INTER_CUBIC)
    out -= out.mean()
    out /= out.std() + 1e-9
    return out


def _static_texture(spec: SceneSpec, ras: _Raster, rng: np.random.Generator) -> np.ndarray:
    """Banks with multi-scale noise, uniform water, GCP checker targets (0..1, float32)."""
    r = spec.river
    scales_m = (0.05, 0.2, 0.8, 3.0)
    scales_px = tuple(max(s / ras.res, 2.0) for s in scales_m)
    tex = spec.bank_gray + spec.bank_contrast * _multiscale_noise(rng, ras.ny, ras.nx, scales_px)
    X, Y = ras.xy()
    wet_rows = (Y > r.y_right_edge) & (Y < r.y_left_edge) & ~r.on_island(r.station_of_y(Y))
    tex[wet_rows, :] = spec.water_gray
    half = spec.gcp_size_m / 2.0
    for gx, gy, _ in gcp_world(spec):
        cols = np.nonzero(np.abs(X - gx) <= half)[0]
        rows = np.nonzero(np.abs(Y - gy) <= half)[0]
        # box-filtered coverage of each texel, so the target's centre is at the GCP to sub-texel accuracy
        fx = np.clip((X[cols] - gx) / ras.res + 0.5, 0.0, 1.0)[None, :]
        fy = np.clip((Y[rows] - gy) / ras.res + 0.5, 0.0, 1.0)[:, None]
        checker = (0.05 + 0.9 * (fx * fy + (1 - fx) * (1 - fy))).astype(np.float32)
        tex[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1] = checker
    return np.clip(tex, 0.0, 1.0).astype(np.float32)


def _shake_matrices(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """(n, 3, 3) image-space rigid motions (rotation about the centre + translation); frame 0 = I."""
    n = spec.n_frames
    M = np.tile(np.eye(3), (n, 1, 1))
    if spec.shake_px <= 0 and spec.shake_deg <= 0 and spec.shake_drift_px_s <= 0:
        return M
    cx, cy = (spec.camera.width_px - 1) / 2.0, (spec.camera.height_px - 1) / 2.0
    heading = rng.uniform(0.0, 2 * np.pi)
    drift = spec.shake_drift_px_s * np.array([np.cos(heading), np.sin(heading)])
    for i in range(1, n):
        t = i / spec.fps
        a = np.radians(rng.normal(0.0, spec.shake_deg) + 0.2 * spec.shake_deg * t)
        tx, ty = rng.normal(0.0, spec.shake_px, 2) + drift * t
        c, s = np.cos(a), np.sin(a)
        M[i] = [[c, -s, cx - c * cx + s * cy + tx], [s, c, cy - s * cx - c * cy + ty], [0, 0, 1]]
    return M


def _bank_regions(spec: SceneSpec, bank_mask: np.ndarray) -> list[list[float]]:
    """Up to four rectangles [x0, y0, x1, y1] (px) lying wholly on the banks: for each bank, the
    tallest band of rows that is bank across each half of the image width."""
    h, w = bank_mask.shape
    rects = []
    margin = w // 20
    halves = [(margin, w // 2 - 8), (w // 2 + 8, w - margin)]
    for label in (1, 2):  # 1 = left bank, 2 = right bank
        for x0, x1 in halves:
            full = np.all(bank_mask[:, x0:x1] == label, axis=1)
            best, start, best_rng = 0, None, None
            for y, f in enumerate(np.append(full, False)):
                if f and start is None:
                    start = y
                elif not f and start is not None:
                    if y - start > best:
                        best, best_rng = y - start, (start, y - 1)
                    start = None
            if best_rng and best >= 24:
                y0, y1 = best_rng[0] + 4, best_rng[1] - 4
                rects.append([float(x0), float(y0), float(x1), float(y1)])
    return rects


def _glint_layers(spec: SceneSpec, rng: np.random.Generator, water_quad_px: np.ndarray) -> np.ndarray:
    """Static sun glints fixed in the image inside ``water_quad_px``: two layers (2, h, w) of
    saturating, horizontally elongated blobs (sigma 2-6 px), each layer flickering on its own."""
    h, w = spec.camera.height_px, spec.camera.width_px
    lo = np.maximum(water_quad_px.min(axis=0), 0)
    hi = np.minimum(water_quad_px.max(axis=0), [w - 1, h - 1])
    poly = water_quad_px.astype(np.float32).reshape(-1, 1, 2)
    layers = np.zeros((2, h, w), np.float32)
    yy, xx = np.mgrid[-20:21, -20:21].astype(np.float32)
    placed = 0
    while placed < spec.glints:
        x, y = rng.uniform(lo, hi)
        if cv2.pointPolygonTest(poly, (float(x), float(y)), False) < 0:
            continue
        sy = rng.uniform(1.5, 3.5)
        sx = sy * rng.uniform(1.5, 3.0)
        blob = rng.uniform(0.9, 1.3) * np.exp(-0.5 * ((xx / sx) ** 2 + (yy / sy) ** 2))
        xi, yi = int(round(x)), int(round(y))
        x0, x1, y0, y1 = max(xi - 20, 0), min(xi + 21, w), max(yi - 20, 0), min(yi + 21, h)
        layers[placed % 2, y0:y1, x0:x1] += blob[y0 - yi + 20 : y1 - yi + 20, x0 - xi + 20 : x1 - xi + 20]
        placed += 1
    return layers


# ---------------------------------------------------------------------------------------------
# hard-scene variants


def _aux_rng(spec: SceneSpec, k: int) -> np.random.Generator:
    """A generator of its own for variant ``k``, so base scenes keep their draws."""
    return np.random.default_rng([spec.seed, 7919, k])


def frame_times(spec: SceneSpec) -> list[float]:
    """Times (s) of the frames written: ``i / fps``; with ``drop_fraction`` > 0 the frames kept from a
    nominal ``fps`` clip after dropping runs of 1-4 frames, jittered by +-2 ms as a phone's
    variable-frame-rate recording, on the container's 10 µs grid (so the timestamps are exact)."""
    n = spec.n_frames
    if spec.drop_fraction <= 0:
        return [i / spec.fps for i in range(n)]

    rng = _aux_rng(spec, 1)
    f = min(max(spec.drop_fraction, 0.0), 0.8)
    p_start = f / (2.5 * (1.0 - f))  # runs of 1-4 frames (mean 2.5)
    keep = np.ones(n, bool)
    i = 2
    while i < n - 1:
        if rng.uniform() < p_start:
            run = int(rng.integers(1, 5))
            keep[i : min(i + run, n - 1)] = False
            i += run + 1
        else:
            i += 1
    t = np.nonzero(keep)[0] / spec.fps
    t[1:] += rng.uniform(-0.002, 0.002, len(t) - 1)
    return [ticks_of(v) * TIMECODE_SCALE_NS * 1e-9 for v in t]


def _patch_keep(spec: SceneSpec, x: np.ndarray, y: np.ndarray, x_lo: float, x_len: float) -> np.ndarray:
    """Particles (initial X, Y in m) that lie in the seeding patches: smooth noise of scale
    ``patch_scale_m`` thresholded so that ``patch_cover`` of the water is seeded."""
    rng = _aux_rng(spec, 2)
    r = spec.river
    g = spec.patch_scale_m / 3.0
    nx = int(np.ceil(x_len / g)) + 2
    ny = int(np.ceil(r.width_m / g)) + 2
    field_ = cv2.GaussianBlur(
        rng.standard_normal((ny, nx)).astype(np.float32), (0, 0), 1.5, borderType=cv2.BORDER_REFLECT
    )
    thr = np.quantile(field_, 1.0 - spec.patch_cover)
    ci = np.clip(((x - x_lo) / g).astype(int), 0, nx - 1)
    ri = np.clip(((r.y_left_edge - y) / g).astype(int), 0, ny - 1)
    return field_[ri, ci] > thr


def _section_glint_layers(spec: SceneSpec) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Sun glints fixed in the image on part of the section: ``spec.section_glints`` saturating,
    elongated blobs (sigma 1-2.5 px) in 12 groups that flicker on and off independently.
    Returns the layers (12, h, w) cropped to their bounding box and that box (x0, y0, x1, y1)."""
    rng = _aux_rng(spec, 3)
    cam, r = spec.camera, spec.river
    h, w = cam.height_px, cam.width_px
    k = 12
    s0, s1 = spec.section_glint_span
    n = spec.section_glints
    X = r.x_section_m + rng.uniform(-spec.section_glint_half_m, spec.section_glint_half_m, n)
    Y = r.y_left_edge - rng.uniform(s0, s1, n) * r.width_m
    px = cam.project(np.column_stack([X, Y, np.full(n, r.level_m)]))
    x0, y0 = np.maximum(np.floor(px.min(axis=0)) - 12, 0).astype(int)
    x1, y1 = np.minimum(np.ceil(px.max(axis=0)) + 13, [w, h]).astype(int)
    layers = np.zeros((k, max(y1 - y0, 1), max(x1 - x0, 1)), np.float32)
    yy, xx = np.mgrid[-10:11, -10:11].astype(np.float32)
    for j, (x, y) in enumerate(px):
        sy = rng.uniform(1.0, 2.5)
        sx = sy * rng.uniform(1.5, 3.0)
        blob = rng.uniform(0.9, 1.4) * np.exp(-0.5 * ((xx / sx) ** 2 + (yy / sy) ** 2))
        xi, yi = int(round(x)) - x0, int(round(y)) - y0
        a0, a1 = max(xi - 10, 0), min(xi + 11, layers.shape[2])
        b0, b1 = max(yi - 10, 0), min(yi + 11, layers.shape[1])
        if a1 > a0 and b1 > b0:
            layers[j % k, b0:b1, a0:a1] += blob[b0 - yi + 10 : b1 - yi + 10, a0 - xi + 10 : a1 - xi + 10]
    return layers, (int(x0), int(y0), int(x1), int(y1))


@dataclass
class _Ripples:
    idx: np.ndarray  # flat canvas indices of the water pixels
    base: np.ndarray  # (k, n) phase at t = 0 (rad)
    rate: np.ndarray  # (k, n) phase rate (rad/s): dispersion + Doppler shift by the flow
    amp: np.ndarray  # (k, n) brightness amplitude after the pixel's integration (0..1)


def _ripples(spec: SceneSpec, offset: tuple[int, int], canvas: tuple[int, int]) -> _Ripples:
    """Wind ripples on the water, drawn on the ideal canvas: ``ripple_waves`` gravity-capillary
    waves (c² = g/k + σk/ρ) travelling at ``ripple_dir_deg`` +- ``ripple_spread_deg`` relative to the
    water, advected by the flow, with an rms brightness ``ripple_amp``. Each wave is attenuated by the
    pixel's integration where it is finer than the pixels (gone beyond Nyquist)."""
    rng = _aux_rng(spec, 4)
    cam, r = spec.camera, spec.river
    cw, ch = canvas
    gx, gy = np.meshgrid(np.arange(cw, dtype=float) - offset[0], np.arange(ch, dtype=float) - offset[1])
    pts, ok = _world_of_pixels(cam, r.level_m, np.column_stack([gx.ravel(), gy.ravel()]))
    X, Y = pts[:, 0].reshape(ch, cw), pts[:, 1].reshape(ch, cw)
    dXy, dXx = np.gradient(X)
    dYy, dYx = np.gradient(Y)
    water = (ok.reshape(ch, cw) & (Y > r.y_right_edge) & (Y < r.y_left_edge)).ravel()
    idx = np.flatnonzero(water)
    Xw, Yw = X.ravel()[idx], Y.ravel()[idx]
    a, b, c, d = dXx.ravel()[idx], dXy.ravel()[idx], dYx.ravel()[idx], dYy.ravel()[idx]
    u = r.surface_velocity_y(Yw)
    k_n = spec.ripple_waves
    lam = np.exp(rng.uniform(np.log(spec.ripple_lambda_m[0]), np.log(spec.ripple_lambda_m[1]), k_n))
    th = np.radians(spec.ripple_dir_deg + rng.uniform(-spec.ripple_spread_deg, spec.ripple_spread_deg, k_n))
    phi = rng.uniform(0.0, 2 * np.pi, k_n)
    wgt = rng.uniform(0.5, 1.0, k_n)
    wgt *= spec.ripple_amp / np.sqrt(0.5 * np.sum(wgt**2))
    kk = 2 * np.pi / lam
    omega = kk * np.sqrt(9.81 / kk + 0.074 / 1000.0 * kk)
    base = np.empty((k_n, idx.size), np.float32)
    rate = np.empty_like(base)
    amp = np.empty_like(base)
    for j in range(k_n):
        kx, ky = kk[j] * np.cos(th[j]), kk[j] * np.sin(th[j])
        base[j] = kx * Xw + ky * Yw + phi[j]
        rate[j] = -(omega[j] + kx * u)
        kap = np.hypot(kx * a + ky * c, kx * b + ky * d)  # rad per pixel
        amp[j] = wgt[j] * np.exp(-0.5 * (0.6 * kap) ** 2) * (kap < np.pi)
    return _Ripples(idx, base, rate, amp)


def _ripple_image(rp: _Ripples, t: float, canvas: tuple[int, int]) -> np.ndarray:
    out = np.zeros(canvas[1] * canvas[0], np.float32)
    acc = np.zeros(rp.idx.size, np.float32)
    for j in range(rp.base.shape[0]):
        acc += rp.amp[j] * np.cos(rp.base[j] + np.float32(t) * rp.rate[j])
    out[rp.idx] = acc
    return out.reshape(canvas[1], canvas[0])


# ---------------------------------------------------------------------------------------------
# rendering


def _open_writer(path: Path, fourcc: str, fps: float, size: tuple[int, int]) -> cv2.VideoWriter:
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), fps, size, True)
    if not wr.isOpened():
        raise ParameterError(f"video writer: this OpenCV build cannot write {fourcc!r} to {path.name}")
    return wr


@dataclass
class _Particles:
    """The tracers on the water (periodic in X over the raster's range) and the raster layer they are splatted
    into: rows ``r0`` .. ``r0 + ly`` of the world raster, ``lx`` columns, mapped to the canvas by ``H_layer``."""

    x0: np.ndarray  # X at t = 0 (m)
    u: np.ndarray  # surface velocity (m/s, along +X)
    cls: np.ndarray  # diameter class
    weight: np.ndarray  # splat weight
    vi: np.ndarray  # layer row (int) and its fraction: particles move along X only
    fv: np.ndarray
    band: np.ndarray | None  # in the band that empties after spec.empty_after_s
    sig_t: list[float]  # blur sigma of each class (raster px)
    n: int
    x_lo: float
    x_len: float
    ly: int
    lx: int
    H_layer: np.ndarray


def _seed_particles(spec: SceneSpec, ras: _Raster, H_static: np.ndarray, rng: np.random.Generator) -> _Particles:
    """Uniform tracers on the water, none on the island nor in the patches left empty (draws from ``rng``)."""
    river = spec.river
    # particle layer: the water rows of the raster plus a blur margin
    Xr, Yr = ras.xy()
    max_d = max(spec.particle_diameters_m)
    pad = int(np.ceil(2 * max_d / ras.res)) + 2
    wet = np.nonzero((Yr > river.y_right_edge) & (Yr < river.y_left_edge))[0]
    r0, r1 = max(wet[0] - pad, 0), min(wet[-1] + pad, ras.ny - 1)
    ly, lx = r1 - r0 + 1, ras.nx
    H_layer = H_static @ np.array([[1.0, 0, 0], [0, 1.0, r0], [0, 0, 1.0]])
    y_layer_top = ras.y_top - r0 * ras.res

    # particles: uniform on the water over the raster's X range (periodic)
    x_lo, x_len = ras.x0, (ras.nx - 1) * ras.res
    n_part = int(round(spec.particle_density_m2 * x_len * river.width_m))
    px0 = rng.uniform(x_lo, x_lo + x_len, n_part)
    py = rng.uniform(river.y_right_edge, river.y_left_edge, n_part)
    pu = river.surface_velocity_y(py)
    n_cls = len(spec.particle_diameters_m)
    cls = rng.integers(0, n_cls, n_part)
    amp = spec.particle_brightness * rng.uniform(0.7, 1.3, n_part)
    if river.island_m is not None:  # no tracer on the island
        keep = ~river.on_island(river.station_of_y(py))
        px0, py, pu, cls, amp = px0[keep], py[keep], pu[keep], cls[keep], amp[keep]
        n_part = int(keep.sum())
    if spec.patch_cover > 0:
        keep = _patch_keep(spec, px0, py, x_lo, x_len)
        px0, py, pu, cls, amp = px0[keep], py[keep], pu[keep], cls[keep], amp[keep]
        n_part = int(keep.sum())
    sig_t = [d / 2.355 / ras.res for d in spec.particle_diameters_m]
    weight = amp * np.array([2 * np.pi * s * s for s in sig_t])[cls]
    v_rows = (y_layer_top - py) / ras.res  # fixed: particles move along X only
    vi = np.floor(v_rows).astype(np.int64)
    fv = v_rows - vi
    band = None
    if spec.empty_after_s > 0 and spec.empty_band_m[1] > spec.empty_band_m[0]:
        s_edge = river.y_left_edge - py
        band = (s_edge >= spec.empty_band_m[0]) & (s_edge <= spec.empty_band_m[1])
    return _Particles(px0, pu, cls, weight, vi, fv, band, sig_t, n_part, x_lo, x_len, ly, lx, H_layer)


def _section_and_gcps(spec: SceneSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(section's two water edges px on frame 0 through the lens, GCP world points, their px)."""
    cam = spec.camera
    sec_world = _section_world(spec)
    gw = gcp_world(spec)
    return cam.project(sec_world), gw, cam.project(gw)


def _section_world(spec: SceneSpec) -> np.ndarray:
    """The section's two water edges on the water plane (X, Y, Z m), skewed by ``section_skew_deg``."""
    river = spec.river
    xs = river.x_section_m
    skew = np.tan(np.radians(spec.section_skew_deg)) * river.width_m / 2.0
    return np.array([[xs + skew, river.y_left_edge, river.level_m], [xs - skew, river.y_right_edge, river.level_m]])


class _FrameRenderer:
    """Draws frame ``i`` at ``t`` (BGR uint8): the tracers advected to ``t``, the static texture, ripples, the
    lens, shake, glints, sensor noise and JPEG loss. Draws the glints' flicker and the noise from ``rng``, in
    frame order."""

    def __init__(
        self,
        spec: SceneSpec,
        ras: _Raster,
        parts: _Particles,
        static_tex: np.ndarray,
        H_static: np.ndarray,
        shake: np.ndarray,
        canvas: tuple[int, int],
        map_x,
        map_y,
        rng: np.random.Generator,
        glint_layers,
        sec_glints,
        flicker_rng: np.random.Generator,
        ripples,
    ):
        cam = spec.camera
        self.spec, self.ras, self.p, self.static_tex, self.H_static = spec, ras, parts, static_tex, H_static
        self.shake, self.canvas, self.map_x, self.map_y, self.rng = shake, canvas, map_x, map_y, rng
        # the glint layers, the section's glints (with their own flicker generator) and the ripples
        self.glint_layers, self.sec_glints, self.flicker_rng, self.ripples = (
            glint_layers,
            sec_glints,
            flicker_rng,
            ripples,
        )
        self.shaken = spec.shake_px > 0 or spec.shake_deg > 0
        self.static_img = None
        if not self.shaken:
            self.static_img = cv2.warpPerspective(
                static_tex, H_static, canvas, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.5
            )
        self.noise = np.empty((cam.height_px, cam.width_px), np.float32)
        self.nuis: Layer | None = None  # low light, rain, shadows, ... (synthetic/nuisances.py), set by render_scene

    def _tracers(self, i: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The tracers splatted, blurred and warped to the canvas; and the frame's shake homography."""
        spec, p, canvas, cam = self.spec, self.p, self.canvas, self.spec.camera
        x = p.x_lo + np.mod(p.x0 - p.x_lo + p.u * t, p.x_len)
        u_cols = (x - self.ras.x0) / self.ras.res
        ui = np.floor(u_cols).astype(np.int64)
        fu = u_cols - ui
        img = np.zeros((canvas[1], canvas[0]), np.float32)
        Hs = self.shake[i] if (self.shaken and not cam.has_distortion) else np.eye(3)
        w_now = (
            p.weight
            if p.band is None
            else np.where(p.band, p.weight * np.clip((spec.empty_after_s + 0.2 - t) / 0.2, 0, 1), p.weight)
        )
        fv, vi, lx, ly, layer_size = p.fv, p.vi, p.lx, p.ly, p.ly * p.lx
        for c in range(len(spec.particle_diameters_m)):
            sel = p.cls == c
            acc = np.zeros(layer_size, np.float64)
            for du, dv, wt in (
                (0, 0, (1 - fu) * (1 - fv)),
                (1, 0, fu * (1 - fv)),
                (0, 1, (1 - fu) * fv),
                (1, 1, fu * fv),
            ):
                cc = np.clip(ui[sel] + du, 0, lx - 1)
                rr = np.clip(vi[sel] + dv, 0, ly - 1)
                acc += np.bincount(rr * lx + cc, weights=(wt[sel] * w_now[sel]), minlength=layer_size)
            layer = cv2.GaussianBlur(acc.reshape(ly, lx).astype(np.float32), (0, 0), p.sig_t[c])
            img += cv2.warpPerspective(
                layer, Hs @ p.H_layer, canvas, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
            )
        return img, Hs

    def render(self, i: int, t: float) -> np.ndarray:
        """Frame ``i`` at ``t`` s, BGR uint8."""
        spec, canvas, cam, shaken = self.spec, self.canvas, self.spec.camera, self.shaken
        w, h = cam.width_px, cam.height_px
        img, Hs = self._tracers(i, t)
        if self.static_img is None:
            img += cv2.warpPerspective(
                self.static_tex,
                Hs @ self.H_static,
                canvas,
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0.5,
            )
        else:
            img += self.static_img
        if self.ripples is not None:
            rip = _ripple_image(self.ripples, t, canvas)
            img += cv2.warpPerspective(rip, Hs, canvas) if shaken and not cam.has_distortion else rip
        if self.nuis is not None:
            img = self.nuis.canvas(img, t)
        if cam.has_distortion:
            img = cv2.remap(
                img, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.5
            )
            if shaken:
                img = cv2.warpAffine(
                    img, self.shake[i][:2], (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
                )
        if self.glint_layers is not None:
            flick = 0.7 + 0.3 * self.rng.uniform(size=2)
            img += flick[0] * self.glint_layers[0] + flick[1] * self.glint_layers[1]
        if self.sec_glints is not None:
            layers, (gx0, gy0, gx1, gy1) = self.sec_glints
            lit = (self.flicker_rng.uniform(size=len(layers)) < spec.glint_duty) * self.flicker_rng.uniform(
                0.6, 1.2, len(layers)
            )
            img[gy0:gy1, gx0:gx1] += np.tensordot(lit.astype(np.float32), layers, axes=1)
        img *= 255.0
        if self.nuis is not None:
            img = self.nuis.sensor(img, t, self.rng)
        if spec.noise_sigma > 0:
            self.noise[:] = self.rng.standard_normal((h, w), dtype=np.float32)
            img += spec.noise_sigma * self.noise
        frame: np.ndarray = np.clip(img + 0.5, 0, 255).astype(np.uint8)
        if spec.jpeg_quality > 0:
            enc = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(spec.jpeg_quality)])[1]
            decoded = cv2.imdecode(enc, cv2.IMREAD_GRAYSCALE)
            assert decoded is not None  # the JPEG just encoded
            frame = decoded
        bgr = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        return bgr if self.nuis is None else self.nuis.colour(bgr, t)


def _write_video(
    spec: SceneSpec,
    video_path: Path,
    times: list[float],
    draw: Callable[[int, float], np.ndarray],
    progress: Callable[[int, int], None] | None,
    cancel: Callable[[], bool] | None,
) -> float:
    """Stream the frames ``draw(i, t)`` into the video (MJPEG in Matroska with dropped frames, else
    ``spec.fourcc``); returns the render+encode seconds per frame."""
    cam = spec.camera
    w, h = cam.width_px, cam.height_px
    writer: MkvWriter | cv2.VideoWriter
    write: Callable[[np.ndarray, float], object]
    if spec.drop_fraction > 0:
        writer = mkv = MkvWriter(video_path, (w, h), quality=95)
        write = mkv.write
    else:
        writer = cvw = _open_writer(video_path, spec.fourcc, spec.fps, (w, h))
        write = lambda img, _t: cvw.write(img)  # noqa: E731
    n = len(times)
    t_start = time.perf_counter()
    try:
        for i, t in enumerate(times):
            if cancel is not None and cancel():
                raise Cancelled("scene rendering cancelled")
            write(draw(i, t), t)
            if progress is not None:
                progress(i + 1, n)
    finally:
        writer.release()
    return (time.perf_counter() - t_start) / max(n, 1)


def _roi_rect(spec: SceneSpec) -> list[float]:
    """ROI: bounding box of the water within x_section +- roi_half_length (sampled edges, lens included)."""
    cam, river = spec.camera, spec.river
    w, h = cam.width_px, cam.height_px
    xs = river.x_section_m
    L = spec.roi_half_length_m
    tt = np.linspace(-L, L, 41)
    ee = np.linspace(river.y_right_edge, river.y_left_edge, 41)
    border = np.vstack(
        [
            np.column_stack([xs + tt, np.full_like(tt, river.y_left_edge), np.full_like(tt, river.level_m)]),
            np.column_stack([xs + tt, np.full_like(tt, river.y_right_edge), np.full_like(tt, river.level_m)]),
            np.column_stack([np.full_like(ee, xs - L), ee, np.full_like(ee, river.level_m)]),
            np.column_stack([np.full_like(ee, xs + L), ee, np.full_like(ee, river.level_m)]),
        ]
    )
    bpx = cam.project(border)
    rx0, ry0 = np.clip(bpx.min(axis=0), 0, [w - 1, h - 1])
    rx1, ry1 = np.clip(bpx.max(axis=0), 0, [w - 1, h - 1])
    return [float(np.floor(rx0)), float(np.floor(ry0)), float(np.ceil(rx1)), float(np.ceil(ry1))]


def _write_project(
    spec: SceneSpec, out: Path, ras: _Raster, sec_px: np.ndarray, gw: np.ndarray, gcp_clicked: np.ndarray, shaken: bool
) -> tuple[Path, Path, Path | None]:
    """What the hydrologist enters: cross_section.csv, project.toml (and checkerboard.mp4 for a distorted
    lens); returns (project, cross-section, checkerboard or None) paths."""
    cam, river = spec.camera, spec.river
    cs = river.survey(spec.survey_spacing_m)
    if spec.section_skew_deg:  # surveyed along the skewed line: stations stretched by 1 / cos
        cs = CrossSection(cs.station / np.cos(np.radians(spec.section_skew_deg)), cs.elevation)
    cs_path = out / "cross_section.csv"
    atomic_write_bytes(cs_path, to_csv_text(cs).encode("utf-8"))
    proj = Project(name=f"synthetic {spec.name}")
    proj.video = VideoCfg(path=spec.video_name)
    proj.cross_section = CrossSectionCfg(path=cs_path.name)
    proj.ortho = OrthoCfg(
        method="distances", gcp_px=_r(gcp_clicked[:4]), distances_m=[round(d, 4) for d in gcp_distances(gw)]
    )
    proj.water_level = WaterLevelCfg(method="value", value_m=float(river.level_m))
    proj.section = SectionCfg(points_px=_r(sec_px), n_sub=spec.n_sub, alpha=float(river.alpha))
    proj.roi = RoiCfg(rect_px=_roi_rect(spec))
    proj.piv = PivCfg(window_px=spec.piv_window_px, overlap_px=spec.piv_overlap_px)
    if shaken:
        proj.stabilize = StabilizeCfg(enabled=True, regions_px=_bank_regions(spec, _bank_mask(spec, ras)))
    cb_path = None
    if cam.has_distortion:
        cb_path = out / "checkerboard.mp4"
        render_checkerboard(
            cam,
            cb_path,
            n_frames=spec.checkerboard_frames,
            square_m=spec.checkerboard_square_m,
            seed=spec.seed + 1,
            fps=spec.fps,
            fourcc=spec.fourcc,
        )
        proj.calibration = CalibrationCfg(
            checkerboard_video=cb_path.name, corners=[9, 6], square_mm=spec.checkerboard_square_m * 1000.0, n_frames=20
        )
    proj_path = out / "project.toml"
    save_project(proj, proj_path)
    return proj_path, cs_path, cb_path


def _section_motion(spec: SceneSpec) -> list[float]:
    """Image motion (px per frame) on the section at 10, 50 and 90 % of the width."""
    cam, river = spec.camera, spec.river
    xs = river.x_section_m
    motion = []
    for frac in (0.1, 0.5, 0.9):
        s = river.s_left + frac * river.width_m
        y = float(river.y_of_station(s))
        u = float(river.surface_velocity(s))
        a = cam.project(np.array([[xs, y, river.level_m], [xs + u / spec.fps, y, river.level_m]]))
        motion.append(float(np.linalg.norm(a[1] - a[0])))
    return motion


def _truth_doc(
    spec: SceneSpec,
    truth: dict,
    res: SceneTruth,
    gcp_clicked: np.ndarray,
    ras: _Raster,
    n_part: int,
    times: list[float],
) -> dict:
    """truth.json: the generator's truth, camera, GCPs and the spec's fields that are set."""
    cam = spec.camera
    doc = {
        **truth,
        "scene": spec.name,
        "n_frames": res.n_frames,
        "fps": spec.fps,
        "timestamps": (
            "container timestamps (Matroska, 10 µs ticks), listed in frame_times_s"
            if spec.drop_fraction > 0
            else "frame i at i / fps seconds"
        ),
        "camera": {
            "K": cam.K.tolist(),
            "R": cam.R.tolist(),
            "t": cam.t.tolist(),
            "rvec": cam.rvec.tolist(),
            "dist": cam.dist_array.tolist(),
            "position_m": list(cam.position_m),
            "target_m": list(cam.target_m),
        },
        "gcp_world_m": res.gcp_world_m.tolist(),
        "gcp_px_exact": res.gcp_px.tolist(),
        "gcp_px_clicked": gcp_clicked.tolist(),
        "section_px": res.section_px.tolist(),
        "section_motion_px_per_frame_at_10_50_90pct": res.section_motion_px,
        "raster_res_m": ras.res,
        "n_particles": n_part,
        "seconds_per_frame": res.seconds_per_frame,
        "codec": "MJPEG in Matroska (variable frame rate)" if spec.drop_fraction > 0 else spec.fourcc,
        "checkerboard_video": res.checkerboard_path.name if res.checkerboard_path else None,
        "spec": _jsonable(
            {
                k: v
                for k, v in asdict(spec).items()
                if (k not in _VARIANT_DEFAULTS or v != _VARIANT_DEFAULTS[k])
                and (k != "nuisances" or spec.nuisances.any)
            }
        ),
    }
    if spec.drop_fraction > 0:
        doc["frame_times_s"] = times
    if spec.section_skew_deg:
        doc["section_note"] = (
            f"section surveyed at {spec.section_skew_deg:g} deg to the flow's normal; "
            "cross-section stations run along it"
        )
    return doc


def render_scene(
    spec: SceneSpec,
    out_dir: Path | str,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> SceneTruth:
    """Render ``spec`` into ``out_dir``: the video, ``cross_section.csv``, ``project.toml`` (what a
    hydrologist would enter) and ``truth.json`` (never read by the pipeline). Distorted cameras
    also get ``checkerboard.mp4``. Frames are streamed to the writer.

    Returns the :class:`SceneTruth`; ``seconds_per_frame`` is the measured render+encode time.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam, river = spec.camera, spec.river
    rng = np.random.default_rng(spec.seed)  # drawn in this order: texture, tracers, shake, glints, frames, clicks
    truth = river.truth()

    # ---- image geometry: ideal canvas (enlarged when the lens distorts) ----
    map_x, map_y, offset, canvas, T = render_canvas(cam)
    H_world = T @ cam.plane_homography(river.level_m)  # world (X, Y) -> canvas px
    ras = _raster_for_view(spec, offset, canvas)
    H_static = H_world @ ras.to_world
    static_tex = _static_texture(spec, ras, rng)
    parts = _seed_particles(spec, ras, H_static, rng)
    shake = _shake_matrices(spec, rng)
    sec_px, gw, g_px = _section_and_gcps(spec)  # section geometry on frame 0 (through the lens)

    glint_layers = None
    if spec.glints > 0:
        xs, L = river.x_section_m, spec.roi_half_length_m
        quad_w = np.array(
            [
                [xs - L, river.y_left_edge - 0.3, river.level_m],
                [xs + L, river.y_left_edge - 0.3, river.level_m],
                [xs + L, river.y_right_edge + 0.3, river.level_m],
                [xs - L, river.y_right_edge + 0.3, river.level_m],
            ]
        )
        glint_layers = _glint_layers(spec, rng, cam.project(quad_w))
    renderer = _FrameRenderer(
        spec,
        ras,
        parts,
        static_tex,
        H_static,
        shake,
        canvas,
        map_x,
        map_y,
        rng,
        glint_layers,
        _section_glint_layers(spec) if spec.section_glints > 0 else None,
        _aux_rng(spec, 5),
        _ripples(spec, offset, canvas) if spec.ripple_amp > 0 else None,
    )
    renderer.nuis = _nuisance_layer(spec, offset, canvas, H_world, _section_world(spec))  # None when it has none

    video_path = out / spec.video_name
    times = frame_times(spec)
    spf = _write_video(spec, video_path, times, renderer.render, progress, cancel)

    gcp_clicked = g_px + rng.normal(0.0, spec.click_error_px, g_px.shape)
    proj_path, cs_path, cb_path = _write_project(spec, out, ras, sec_px, gw, gcp_clicked, renderer.shaken)
    res = SceneTruth(
        discharge_m3s=truth["discharge_m3s"],
        water_level_m=river.level_m,
        alpha=river.alpha,
        wetted_width_m=truth["wetted_width_m"],
        wetted_area_m2=truth["wetted_area_m2"],
        mean_velocity_ms=truth["mean_velocity_ms"],
        K=cam.K.copy(),
        R=cam.R.copy(),
        t=cam.t.copy(),
        dist=cam.dist_array.copy(),
        gcp_world_m=gw,
        gcp_px=g_px,
        section_px=sec_px,
        video_path=video_path,
        project_path=proj_path,
        cross_section_path=cs_path,
        truth_path=out / "truth.json",
        n_frames=len(times),
        fps=spec.fps,
        seconds_per_frame=spf,
        section_motion_px=_section_motion(spec),
        checkerboard_path=cb_path,
        spec=spec,
    )
    truth_doc = _truth_doc(spec, truth, res, gcp_clicked, ras, parts.n, times)
    atomic_write_bytes(res.truth_path, json.dumps(truth_doc, indent=2).encode("utf-8"))
    return res


_VARIANT_FIELDS = (
    "patch_cover",
    "patch_scale_m",
    "empty_band_m",
    "empty_after_s",
    "section_glints",
    "section_glint_span",
    "section_glint_half_m",
    "glint_duty",
    "ripple_amp",
    "ripple_dir_deg",
    "ripple_spread_deg",
    "ripple_lambda_m",
    "ripple_waves",
    "section_skew_deg",
    "jpeg_quality",
    "drop_fraction",
)
# truth.json lists a variant field only when it is set, so the base scenes' files stay as they were
_VARIANT_DEFAULTS = {k: SceneSpec.__dataclass_fields__[k].default for k in _VARIANT_FIELDS}


def _nuisance_layer(
    spec: SceneSpec, offset: tuple[int, int], canvas: tuple[int, int], H_world: np.ndarray, sec_world: np.ndarray
) -> Layer | None:
    """The scene's nuisances prepared on its canvas (world X, Y of each canvas pixel), or None."""
    if not spec.nuisances.any:
        return None
    cw, ch = canvas
    gx, gy = np.meshgrid(np.arange(cw, dtype=np.float32) - offset[0], np.arange(ch, dtype=np.float32) - offset[1])
    pts, ok = _world_of_pixels(spec.camera, spec.river.level_m, np.column_stack([gx.ravel(), gy.ravel()]))
    X = np.where(ok, pts[:, 0], np.nan).reshape(ch, cw).astype(np.float32)
    Y = np.where(ok, pts[:, 1], np.nan).reshape(ch, cw).astype(np.float32)
    p = np.column_stack([sec_world[:, :2], np.ones(2)]) @ H_world.T
    sec_canvas = p[:, :2] / p[:, 2:3]
    return Layer(
        spec.nuisances, spec.seed, spec.river, np.stack([X, Y]), H_world, sec_canvas, spec.fps, spec.roi_half_length_m
    )


def _bank_mask(spec: SceneSpec, ras: _Raster) -> np.ndarray:
    """Frame-0 image labels: 1 left bank, 2 right bank, 0 water / outside the raster / near GCPs."""
    cam, r = spec.camera, spec.river
    h, w = cam.height_px, cam.width_px
    xs, ys = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    ideal = cam.undistorted_of_distorted(np.column_stack([xs.ravel(), ys.ravel()]))
    pts, ok = _world_of_pixels(cam, r.level_m, ideal)
    X, Y = pts[:, 0], pts[:, 1]
    inside = (
        ok
        & (X > ras.x0 + 1)
        & (X < ras.x0 + ras.res * ras.nx - 1)
        & (Y < ras.y_top - 1)
        & (Y > ras.y_top - ras.res * ras.ny + 1)
    )
    lab = np.zeros(len(X), np.uint8)
    lab[inside & (Y > r.y_left_edge + 0.5)] = 1
    lab[inside & (Y < r.y_right_edge - 0.5)] = 2
    return lab.reshape(h, w)


def _r(a: np.ndarray) -> list[list[float]]:
    return [[round(float(v), 3) for v in row] for row in np.asarray(a)]


def _jsonable(o):
    if isinstance(o, dict):
        return {k: _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return o
