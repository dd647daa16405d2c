"""Named synthetic scenes. ``get(name, **overrides) -> SceneSpec``.

Base scenes (a river 12 m wide, up to 1.5 m deep, ~1.2 m/s at the surface, 5 s at 30 fps, 1280x720):

- ``oblique``: bank camera 6 m above the water, 8 m back from the left water edge, looking across
  and slightly downstream (the demo).
- ``nadir``: drone 25 m above the water, looking straight down, flow left to right.
- ``far_bank``: low camera (3 m above the water, 8 m back from the right edge); the far (left) side of
  the river is seen at a grazing angle (~8.5 degrees at the far edge); steeper far bank, 1.4 m/s.

Variant flags, combinable: ``shake=True`` (random translation ~3 px + rotation ~0.3 deg per frame on a drift of 20 px/s,
frame 0 unshaken; the project enables stabilisation on bank regions), ``distortion=True``
(barrel k1 = -0.25, k2 = 0.03 with a rendered 9x6 checkerboard video of the same camera),
``glints=True`` (40 static, flickering sun glints on the water near the section), ``lens_gcps=True`` (a strong
barrel lens and 8 GCPs, to fit the lens from them).

Hard scenes (8 s, 1280x720 unless noted; :data:`HARD_NAMES`), each a variant of the ones above with its
truth integrated from the profile it draws (``River.truth()``), deterministic by seed:

- ``glints_section``: oblique view; ~160 sun glints flickering in place (on/off in 12 groups) over the middle
  half of the section, +-1.2 m up/downstream; tracers only 15-25 grey levels above the water.
- ``ripples``: oblique view; sparse tracers (1 /m², 10 cm) under wind ripples (8-50 cm gravity-capillary
  waves, rms 10 grey levels) travelling against and across the flow (160 +- 40 degrees) and advected by it.
- ``sparse_patchy``: oblique view; natural seeding in patches (~1.5 m) covering 35 % of the water (~2 /m²
  on average); the band 0-3 m from the near (left) bank empties after 3 s.
- ``fast_1080p``: 3.2 m/s, 1920x1080 at 25 fps, telephoto bank camera: ~22 px/frame near the camera.
- ``grazing``: camera 2 m above a 25 m wide river (3.5 degrees at the far edge).
- ``compressed``: oblique view, every frame through JPEG quality 12, then MPEG-4 Part 2.
- ``skewed``: oblique view, section surveyed at 25 degrees to the flow's normal.
- ``dropped_frames``: oblique view as a variable-frame-rate Matroska (MJPEG) clip: ~20 % of the frames of a
  30 fps recording dropped in runs of 1-4, +-2 ms jitter; container timestamps exact (10 µs ticks).

Unseen scenes (:data:`NEW_NAMES`, 6 s; synthetic/nuisances.py draws them), each on a base view chosen by the
seed (seed % 3: oblique, nadir, far_bank; ``drone_4k`` always nadir) so that seeds vary the geometry too, with
the nuisances' positions drawn from the seed:

- ``low_light``: dusk; water at 22 grey levels, tracers 6-10 levels above it, shot + read noise ~5 levels at
  the water, vignetting 30 % at the corners.
- ``glare_column``: a column of one-frame glitter (~400 glints a frame) across the middle of the section, faint
  tracers (~13 levels) under a bright haze.
- ``rain``: raindrop rings born at fixed points (not advected), spreading at 0.35 m/s, plus streaks in the air.
- ``shadows``: a hard bridge shadow band fixed in the world near the section plus swaying leaf shadows.
- ``exposure``: auto-exposure pumping (gain 0.8-1.25, 2 s cycle and steps) and a white-balance drift.
- ``debris``: sparse seeding (4 /m²) with 8 large floating objects (0.3-0.9 m) moving with the surface.
- ``standing_waves``: a standing wave train and a hydraulic jump's foam roller, both fixed in the world.
- ``drone_4k``: a 3840x2160 drone looking straight down from 25 m.

Any other keyword replaces a :class:`SceneSpec` field (``seed=3``, ``duration_s=4``); ``river__x``
and ``camera__x`` replace a field of the river or the camera (``river__u_max_ms=0.9``).
"""

from __future__ import annotations

from dataclasses import replace

from fieldtool.errors import ParameterError
from fieldtool.synthetic.camera import Camera
from fieldtool.synthetic.nuisances import Nuisances
from fieldtool.synthetic.scene import River, SceneSpec

NAMES = ("oblique", "nadir", "far_bank")
DISTORTION = (-0.25, 0.03, 0.0, 0.0, 0.0)


def _oblique() -> SceneSpec:
    r = River()
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs - 3.0, r.y_left_edge + 8.0, lv + 6.0), target_m=(xs + 2.0, 3.2, lv), hfov_deg=70.0)
    return SceneSpec(
        name="oblique",
        river=r,
        camera=cam,
        particle_density_m2=20.0,
        particle_diameters_m=(0.07,),
        texture_res_m=0.015,
        piv_window_px=32,
        piv_overlap_px=16,
    )


def _nadir() -> SceneSpec:
    r = River()
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs, 0.0, lv + 25.0), target_m=(xs, 0.0, lv), hfov_deg=60.0, up_hint=(0.0, 1.0, 0.0))
    return SceneSpec(
        name="nadir",
        river=r,
        camera=cam,
        particle_density_m2=16.0,
        particle_diameters_m=(0.08,),
        texture_res_m=0.02,
        piv_window_px=32,
        piv_overlap_px=16,
    )


def _far_bank() -> SceneSpec:
    r = River(shape_a=0.7, shape_b=1.2, u_max_ms=1.4)
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs - 0.5, r.y_right_edge - 8.0, lv + 3.0), target_m=(xs + 0.5, -3.1, lv), hfov_deg=50.0)
    return SceneSpec(
        name="far_bank",
        river=r,
        camera=cam,
        particle_density_m2=10.0,
        gcp_half_dx_m=2.5,
        particle_diameters_m=(0.10,),
        texture_res_m=0.02,
        piv_window_px=32,
        piv_overlap_px=16,
    )


_BASE = {"oblique": _oblique, "nadir": _nadir, "far_bank": _far_bank}

HARD_NAMES = (
    "glints_section",
    "ripples",
    "sparse_patchy",
    "fast_1080p",
    "grazing",
    "compressed",
    "skewed",
    "dropped_frames",
)
HARD_DURATION_S = 8.0


def _glints_section() -> SceneSpec:
    return replace(_oblique(), particle_brightness=0.08, section_glints=160, section_glint_span=(0.25, 0.75))


def _ripples() -> SceneSpec:
    return replace(
        _oblique(),
        particle_density_m2=1.0,
        particle_diameters_m=(0.10,),
        ripple_amp=0.04,
        ripple_dir_deg=160.0,
        ripple_spread_deg=40.0,
        ripple_lambda_m=(0.08, 0.5),
    )


def _sparse_patchy() -> SceneSpec:
    return replace(
        _oblique(),
        particle_density_m2=6.0,
        particle_diameters_m=(0.06, 0.10),
        patch_cover=0.35,
        patch_scale_m=1.5,
        empty_band_m=(0.0, 3.0),
        empty_after_s=3.0,
    )


def _fast_1080p() -> SceneSpec:
    r = River(u_max_ms=3.2, shape_a=0.6, shape_b=0.8)
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(
        position_m=(xs - 2.0, r.y_left_edge + 10.0, lv + 5.0),
        target_m=(xs + 1.0, 0.8, lv),
        hfov_deg=40.0,
        width_px=1920,
        height_px=1080,
    )
    return SceneSpec(
        name="fast_1080p",
        river=r,
        camera=cam,
        fps=25.0,
        particle_density_m2=20.0,
        gcp_half_dx_m=2.0,
        particle_diameters_m=(0.06,),
        texture_res_m=0.01,
        piv_window_px=32,
        piv_overlap_px=16,
    )


def _grazing() -> SceneSpec:
    r = River(width_m=25.0, depth_m=2.5, shape_a=1.0, shape_b=0.8, u_max_ms=1.5)
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs - 3.0, r.y_left_edge + 8.0, lv + 2.0), target_m=(xs + 2.0, -2.0, lv), hfov_deg=60.0)
    return SceneSpec(
        name="grazing",
        river=r,
        camera=cam,
        particle_density_m2=10.0,
        gcp_half_dx_m=3.0,
        particle_diameters_m=(0.10,),
        texture_res_m=0.02,
        piv_window_px=32,
        piv_overlap_px=16,
    )


def _compressed() -> SceneSpec:
    return replace(_oblique(), jpeg_quality=12)


def _skewed() -> SceneSpec:
    return replace(_oblique(), section_skew_deg=25.0, roi_half_length_m=5.0)


def _dropped_frames() -> SceneSpec:
    return replace(_oblique(), drop_fraction=0.2, video_name="river.mkv")


_HARD = {
    "glints_section": _glints_section,
    "ripples": _ripples,
    "sparse_patchy": _sparse_patchy,
    "fast_1080p": _fast_1080p,
    "grazing": _grazing,
    "compressed": _compressed,
    "skewed": _skewed,
    "dropped_frames": _dropped_frames,
}


NEW_NAMES = ("low_light", "glare_column", "rain", "shadows", "exposure", "debris", "standing_waves", "drone_4k")
NEW_DURATION_S = 6.0


def _base_by_seed(seed: int) -> SceneSpec:
    """The base view of an unseen scene: oblique, nadir, far_bank for seed % 3 = 0, 1, 2."""
    return (_oblique, _nadir, _far_bank)[int(seed) % 3]()


def _low_light(seed: int) -> SceneSpec:
    return replace(
        _base_by_seed(seed),
        water_gray=22 / 255,
        bank_gray=0.16,
        bank_contrast=0.06,
        particle_brightness=8 / 255,
        noise_sigma=0.0,
        nuisances=Nuisances(read_noise=4.0, shot_gain=0.41, vignette=0.3),
    )


def _glare_column(seed: int) -> SceneSpec:
    return replace(
        _base_by_seed(seed),
        particle_brightness=0.05,
        nuisances=Nuisances(glitter_per_frame=400, glitter_halfwidth_px=50.0, haze=0.35),
    )


def _rain(seed: int) -> SceneSpec:
    return replace(_base_by_seed(seed), nuisances=Nuisances(rain_rate_m2s=3.0, rain_streaks=60))


def _shadows(seed: int) -> SceneSpec:
    return replace(_base_by_seed(seed), nuisances=Nuisances(shadow_band_depth=0.6, leaf_shadows=12))


def _exposure(seed: int) -> SceneSpec:
    return replace(_base_by_seed(seed), nuisances=Nuisances(exposure_amp=0.2, white_balance_amp=0.15))


def _debris(seed: int) -> SceneSpec:
    return replace(_base_by_seed(seed), particle_density_m2=4.0, nuisances=Nuisances(debris=8))


def _standing_waves(seed: int) -> SceneSpec:
    return replace(_base_by_seed(seed), nuisances=Nuisances(standing_amp=0.06, jump_amp=0.15))


def _drone_4k(seed: int) -> SceneSpec:
    s = _nadir()
    cam = replace(s.camera, width_px=3840, height_px=2160)
    return replace(s, camera=cam, texture_res_m=0.006, particle_diameters_m=(0.06,))


_NEW = {
    "low_light": _low_light,
    "glare_column": _glare_column,
    "rain": _rain,
    "shadows": _shadows,
    "exposure": _exposure,
    "debris": _debris,
    "standing_waves": _standing_waves,
    "drone_4k": _drone_4k,
}


STRONG_DISTORTION = (-0.35, 0.03675, 0.0, 0.0, 0.0)


def get(
    name: str,
    *,
    shake: bool = False,
    distortion: bool = False,
    glints: bool = False,
    lens_gcps: bool = False,
    **overrides,
) -> SceneSpec:
    """The scene ``name`` (one of :data:`NAMES`, :data:`HARD_NAMES` or :data:`NEW_NAMES`) with variant flags and field
    overrides applied. Hard scenes last :data:`HARD_DURATION_S` unless ``duration_s`` is given.

    ``lens_gcps=True``: a strong barrel lens (k1 -0.35, k2 0.037, 62 degrees) aimed so the section lies
    off the image centre, and 4 more GCP targets on the banks (8 in all) to fit the lens from them.
    """
    if name in _HARD:
        spec = replace(_HARD[name](), name=name, duration_s=HARD_DURATION_S)
    elif name in _NEW:  # the seed chooses the base view
        spec = replace(_NEW[name](int(overrides.get("seed", 0))), name=name, duration_s=NEW_DURATION_S)
    elif name in _BASE:
        spec = _BASE[name]()
    else:
        raise ParameterError(f"synthetic scene {name!r}: choose one of {', '.join(NAMES + HARD_NAMES + NEW_NAMES)}")
    suffix = []
    if shake:
        spec = replace(spec, shake_px=3.0, shake_deg=0.3, shake_drift_px_s=20.0)
        suffix.append("shake")
    if distortion:
        # a longer focal length keeps the barrel-distorted view close to the pinhole one
        spec = replace(spec, camera=replace(spec.camera, hfov_deg=min(spec.camera.hfov_deg, 60.0), dist=DISTORTION))
        suffix.append("distortion")
    if lens_gcps:
        cam = spec.camera
        target = (cam.target_m[0] - 1.5, cam.target_m[1], cam.target_m[2])
        spec = replace(spec, camera=replace(cam, hfov_deg=62.0, dist=STRONG_DISTORTION, target_m=target), extra_gcps=4)
        suffix.append("lens_gcps")
    if glints:
        spec = replace(spec, glints=40)
        suffix.append("glints")
    if suffix:
        spec = replace(spec, name="_".join([name, *suffix]))
    try:
        return spec.with_(**overrides)
    except TypeError as e:
        raise ParameterError(f"synthetic scene {name!r}: {e}") from e
