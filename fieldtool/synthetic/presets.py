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

Any other keyword replaces a :class:`SceneSpec` field (``seed=3``, ``duration_s=4``); ``river__x``
and ``camera__x`` replace a field of the river or the camera (``river__u_max_ms=0.9``).
"""

from __future__ import annotations

from dataclasses import replace

from ..errors import ParameterError
from .camera import Camera
from .scene import River, SceneSpec

NAMES = ("oblique", "nadir", "far_bank")
DISTORTION = (-0.25, 0.03, 0.0, 0.0, 0.0)


def _oblique() -> SceneSpec:
    r = River()
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs - 3.0, r.y_left_edge + 8.0, lv + 6.0), target_m=(xs + 2.0, 3.2, lv), hfov_deg=70.0)
    return SceneSpec(name="oblique", river=r, camera=cam, particle_density_m2=20.0,
                     particle_diameters_m=(0.07,), texture_res_m=0.015, piv_window_px=32, piv_overlap_px=16)


def _nadir() -> SceneSpec:
    r = River()
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs, 0.0, lv + 25.0), target_m=(xs, 0.0, lv), hfov_deg=60.0, up_hint=(0.0, 1.0, 0.0))
    return SceneSpec(name="nadir", river=r, camera=cam, particle_density_m2=16.0,
                     particle_diameters_m=(0.08,), texture_res_m=0.02, piv_window_px=32, piv_overlap_px=16)


def _far_bank() -> SceneSpec:
    r = River(shape_a=0.7, shape_b=1.2, u_max_ms=1.4)
    xs, lv = r.x_section_m, r.level_m
    cam = Camera(position_m=(xs - 0.5, r.y_right_edge - 8.0, lv + 3.0), target_m=(xs + 0.5, -3.1, lv), hfov_deg=50.0)
    return SceneSpec(name="far_bank", river=r, camera=cam, particle_density_m2=10.0, gcp_half_dx_m=2.5,
                     particle_diameters_m=(0.10,), texture_res_m=0.02, piv_window_px=32, piv_overlap_px=16)


_BASE = {"oblique": _oblique, "nadir": _nadir, "far_bank": _far_bank}


STRONG_DISTORTION = (-0.35, 0.03675, 0.0, 0.0, 0.0)


def get(name: str, *, shake: bool = False, distortion: bool = False, glints: bool = False, lens_gcps: bool = False,
        **overrides) -> SceneSpec:
    """The scene ``name`` (one of :data:`NAMES`) with variant flags and field overrides applied.

    ``lens_gcps=True``: a strong barrel lens (k1 -0.35, k2 0.037, 62 degrees) aimed so the section lies
    off the image centre, and 4 more GCP targets on the banks (8 in all) to fit the lens from them.
    """
    if name not in _BASE:
        raise ParameterError(f"synthetic scene {name!r}: choose one of {', '.join(NAMES)}")
    spec = _BASE[name]()
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
