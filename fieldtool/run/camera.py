"""The camera check before the PIV: did the camera move in the clip's first frames, seen at the GCPs?

A handheld clip, a settling tripod or a hovering drone moves the picture, and without ``[stabilize]`` the PIV
reads the camera's motion as the water's. The GCPs are fixed ground, so patches around them are followed over
the first :data:`N_FRAMES` frames, the frames the clip check reads anyway (processing/camera_motion.py). Where
the camera moved and the user did not ask for stabilisation, the run stabilises on those patches itself
(processing/stabilize.py, the thesis' regions around the GCPs), once that registration holds on the first
frames; where it does not hold, the run goes on unstabilised, says why and grades the measurement doubtful.
``result.json`` reports the check under ``robust.camera``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

from fieldtool.errors import FieldToolError, GeometryError
from fieldtool.processing import camera_motion
from fieldtool.processing.quality import Reason
from fieldtool.processing.stabilize import Stabilizer
from fieldtool.project.model import Project
from fieldtool.run.clip_check import N_FRAMES  # the frames looked at: the clip check's, read once for both
from fieldtool.run.inputs import Inputs


@dataclass
class Camera:
    """The check's outcome: ``motion`` (None: not checked, with ``why``), whether it switched the stabilisation
    on (``stabilized``, on ``regions_px``, raw-frame px) and, where the camera moved but the registration did not
    hold, ``problem``."""

    motion: camera_motion.CameraMotion | None
    why: str = ""
    stabilized: bool = False
    regions_px: list[list[float]] = field(default_factory=list)
    problem: str | None = None

    def facts(self) -> dict:
        out: dict = {"checked": self.motion is not None}
        if self.motion is None:
            out["why_not"] = self.why
            return out
        out.update(self.motion.to_dict())
        out["stabilized"] = self.stabilized
        if self.stabilized:
            out["regions_px"] = self.regions_px
        if self.problem:
            out["problem"] = self.problem
        return out


def boxes(project: Project, inputs: Inputs) -> list[tuple[int, int, int, int]]:
    """The patches (x0, y0, x1, y1 raw-frame px) followed around the GCPs; none where the user stabilises, where
    there are no GCPs, or fewer than two lie whole in the frame."""
    if project.stabilize.enabled or not project.stabilize.auto or not project.ortho.gcp_px:
        return []
    got = camera_motion.patch_boxes(project.ortho.gcp_px, inputs.shape)
    return got if len(got) >= 2 else []


def check(project: Project, inputs: Inputs, head, patch_boxes, warnings: list[str]) -> tuple[Project, Camera]:
    """The project to run (stabilised on the GCPs' patches where the camera moved and the registration holds)
    and the check's :class:`Camera`. ``head``: the clip's first frames as ``FrameSource.head`` gave them with
    ``patch_boxes`` (:func:`boxes`)."""
    if project.stabilize.enabled:
        return project, Camera(None, "stabilize.enabled: the user's registration")
    if not project.stabilize.auto:
        return project, Camera(None, "stabilize.auto = false: the frames as filmed")
    if not patch_boxes:
        return project, Camera(None, "fewer than two GCPs lie whole in the frame")
    patches = [list(f.patches) for f in head if f.patches is not None]
    motion = camera_motion.measure(patches)
    if motion.points < 2 or len(motion.agree) < 2:
        return project, Camera(None, "too few GCPs with texture to follow (fewer than two stayed put or moved)")
    cam = Camera(motion)
    if not motion.moved:
        return project, cam
    regions = [[float(c) for c in patch_boxes[i]] for i in motion.agree]
    said = (
        f"the camera moved up to {motion.max_shift_px:.2f} px in the first {motion.frames} frames (at "
        f"{len(motion.agree)} of the {motion.points} GCPs followed, and fewer than two stayed put; a GCP moved beyond "
        f"{motion.threshold_px:.2f} px, five times the tracking noise of {motion.noise_px:.3f} px or 0.1 px)"
    )
    try:
        _registers(project, inputs, regions)
    except FieldToolError as e:
        cam.problem = str(e)
        warnings.append(
            f"stabilize: {said}, but registering the frames on patches around those GCPs did not hold ({e}); the "
            "run goes on unstabilised and the camera's motion is in the velocities: draw stabilize.regions_px on "
            "fixed, textured ground and set stabilize.enabled = true"
        )
        return project, cam
    cam.stabilized, cam.regions_px = True, regions
    warnings.append(
        f"stabilize: {said}: every frame is registered on patches around those GCPs; set [stabilize] to choose "
        "yourself (stabilize.auto = false keeps the frames as filmed)"
    )
    st = replace(project.stabilize, enabled=True, regions_px=regions, water_polygon_px=[])
    return replace(project, stabilize=st), cam


def _registers(project: Project, inputs: Inputs, regions: list[list[float]]) -> None:
    """Register the clip's first frames (whole, decoded again: the check's were read in the PIV's box) on
    ``regions`` as the run would; raises what :class:`Stabilizer` raises where it does not hold."""
    imgs = [f.image for f in inputs.source.head(N_FRAMES) if f.image is not None]
    if inputs.lens is not None:
        imgs = [inputs.lens.undistort(i) for i in imgs]
    working = [inputs.to_working([[r[0], r[1]], [r[2], r[3]]]).ravel().tolist() for r in regions]
    st = project.stabilize
    stab = Stabilizer(imgs[0], regions_px=working, model=st.model, max_drift_px=st.max_drift_px)
    for img in imgs[1:]:
        stab.register(img)


@contextlib.contextmanager
def explained(cam: Camera) -> Iterator[None]:
    """Around the frames' pass: where this check switched the stabilisation on and the registration fails later
    in the clip (a GCP hidden, the camera moved too far), the error says that the regions were the run's own, not
    the user's, and what to set (exit 2, as for the user's regions)."""
    try:
        yield
    except GeometryError as e:
        if not cam.stabilized:
            raise
        raise GeometryError(
            f"stabilize (switched on by the camera check, on patches around the GCPs): {e}. Draw "
            "stabilize.regions_px on fixed ground and set stabilize.enabled = true, or set stabilize.auto = false "
            "to measure the frames as filmed"
        ) from e


def add_reason(quality, facts: dict | None) -> None:
    """The camera moved and the run could not stabilise: a doubtful verdict (a good grade becomes doubtful)."""
    if quality is None or not facts or not facts.get("moved") or facts.get("stabilized"):
        return
    quality.reasons.append(
        Reason(
            "camera_moved",
            "doubtful",
            f"the camera moved up to {facts['max_shift_px']:.2f} px in the first frames and the frames could not "
            "be registered on the GCPs: the velocities carry the camera's motion; set [stabilize]",
            facts["max_shift_px"],
            facts["threshold_px"],
        )
    )
    if quality.grade == "good":
        quality.grade = "doubtful"
