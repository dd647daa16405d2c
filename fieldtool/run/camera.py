"""The camera check before the PIV: did the camera move in the clip's first frames, seen at the GCPs?

A handheld clip, a settling tripod or a hovering drone moves the picture, and without ``[stabilize]`` the PIV
reads the camera's motion as the water's. The GCPs are fixed ground, so patches around them are followed over
the first :data:`N_FRAMES` frames, the frames the clip check reads anyway (processing/camera_motion.py). Where
the camera moved and the user did not ask for stabilisation, the run stabilises on those patches itself
(processing/stabilize.py, the thesis' regions around the GCPs), once that registration holds on the first
frames; where it does not hold, the run goes on unstabilised, says why and grades the measurement doubtful.
The same patches are then kept for every few frames the run's pass decodes (``FrameSource.watch``: about
:data:`LATER_FRAMES` of them over the clip). Where the camera was still at first, :func:`later` checks, after the
pass and in a thread of its own beside the discharge (:class:`Later`), that the GCPs which stayed put still do: a
tripod bumped halfway through is said in a warning and the verdict (doubtful, ``camera_moved``), with the regions
to stabilise on. ``result.json`` reports the check under ``robust.camera``.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

from fieldtool.errors import FieldToolError, GeometryError
from fieldtool.processing import camera_motion
from fieldtool.processing.quality import Reason
from fieldtool.project.model import Project
from fieldtool.run.clip_check import N_FRAMES  # the frames looked at: the clip check's, read once for both
from fieldtool.run.frames import make_stabilizer
from fieldtool.run.inputs import Inputs

#: frames of the rest of the clip whose patches are kept for :func:`later` (every few frames, at least every 5th)
LATER_FRAMES = 24


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
    boxes: list = field(default_factory=list)  # the patches followed (raw-frame px), one per GCP that fits
    later: dict | None = None  # the rest of the clip (:func:`later`)

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
        if self.later is not None:
            out["later"] = self.later
        return out


def boxes(project: Project, inputs: Inputs) -> list[tuple[int, int, int, int]]:
    """The patches (x0, y0, x1, y1 raw-frame px) followed around the GCPs; none where the user stabilises, where
    there are no GCPs, or fewer than two lie whole in the frame."""
    if project.stabilize.enabled or not project.stabilize.auto or not project.ortho.gcp_px:
        return []
    got = camera_motion.patch_boxes(project.ortho.gcp_px, inputs.shape)
    return got if len(got) >= 2 else []


def watch(project: Project, inputs: Inputs) -> list[tuple[int, int, int, int]]:
    """:func:`boxes`, and the clip's frames made to keep their crops: the first :data:`N_FRAMES`, then every few
    (``FrameSource.watch``). Before the first frame is read."""
    got = boxes(project, inputs)
    n = inputs.source.estimated_count() or 0
    inputs.source.watch(got or None, first=N_FRAMES, every=max(5, -(-(n - N_FRAMES) // LATER_FRAMES)))
    return got


def check(project: Project, inputs: Inputs, head, patch_boxes, warnings: list[str]) -> tuple[Project, Camera]:
    """The project to run (stabilised on the GCPs' patches where the camera moved and the registration holds)
    and the check's :class:`Camera`. ``head``: the clip's first frames (``FrameSource.head``), read after
    :func:`watch` gave ``patch_boxes``."""
    if project.stabilize.enabled:
        return project, Camera(None, "stabilize.enabled: the user's registration")
    if not project.stabilize.auto:
        return project, Camera(None, "stabilize.auto = false: the frames as filmed")
    if not patch_boxes:
        return project, Camera(None, "fewer than two GCPs lie whole in the frame")
    seen = inputs.source.watched
    patches = [list(seen[k][1]) for k in range(len(head)) if k in seen]
    motion = camera_motion.measure(patches)
    if motion.points < 2 or len(motion.agree) < 2:
        return project, Camera(None, "too few GCPs with texture to follow (fewer than two stayed put or moved)")
    cam = Camera(motion, boxes=list(patch_boxes))
    if not motion.moved:
        return project, cam
    regions = [[float(c) for c in patch_boxes[i]] for i in motion.agree]
    stabilised = replace(
        project, stabilize=replace(project.stabilize, enabled=True, regions_px=regions, water_polygon_px=[])
    )
    said = (
        f"the camera moved up to {motion.max_shift_px:.2f} px in the first {motion.frames} frames (at "
        f"{len(motion.agree)} of the {motion.points} GCPs followed, and fewer than two stayed put; a GCP moved beyond "
        f"{motion.threshold_px:.2f} px, five times the tracking noise of {motion.noise_px:.3f} px or 0.1 px)"
    )
    try:
        _registers(stabilised, inputs)
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
    return stabilised, cam


def later(cam: Camera, inputs: Inputs, warnings: list[str]) -> None:
    """After the pass: where the camera was still in the first frames and nothing registered the frames, do the
    GCPs that stayed put still stay put in the rest of the clip (the patches ``FrameSource.watch`` kept)? Sets
    ``cam.later``; a camera that moved is said in ``warnings`` and, through the facts, in the verdict."""
    seen, first = inputs.source.watched, inputs.source.watch_first  # first: N_FRAMES, or fewer after a step
    inputs.source.watch(None)
    m = cam.motion
    rest = sorted(k for k in seen if k >= first)
    if m is None or m.moved or cam.stabilized or not rest or 0 not in seen:
        return
    keep = list(m.agree)  # the points that stayed put in the first frames
    patches = [[seen[0][1][i] for i in keep]] + [[seen[k][1][i] for i in keep] for k in rest]
    after = camera_motion.measure(patches)
    cam.later = {"frames": len(rest), "checked": after.points >= 2, "moved": bool(after.moved)}
    if not after.moved:
        return
    first = next((j for j, d in enumerate(after.moved_px[1:]) if d > after.threshold_px), 0)
    t0 = float(seen[rest[first]][0])
    regions = [[float(c) for c in cam.boxes[keep[i]]] for i in after.agree]
    cam.later.update(
        from_s=round(t0, 3),
        max_shift_px=round(after.max_shift_px, 3),
        threshold_px=round(after.threshold_px, 3),
        regions_px=regions,
    )
    warnings.append(
        f"stabilize: the camera moved later in the clip: the GCPs that stayed put in the first {m.frames} frames moved "
        f"by up to {after.max_shift_px:.2f} px from {t0:.2f} s on (beyond {after.threshold_px:.2f} px); the velocities "
        f"carry it. Set stabilize.enabled = true and stabilize.regions_px = {regions} (patches around those GCPs) "
        "and run again"
    )


class Later:
    """:func:`later` in a thread of its own, started after the pass, beside the discharge and STIV's analysis
    (Lucas-Kanade releases the GIL): 40-80 ms of a run's critical path otherwise. :meth:`join` before the verdict
    adds its warning and ``robust.camera``, in that order whatever the timing."""

    def __init__(self, cam: Camera, inputs: Inputs):
        self.cam, self.said = cam, list[str]()
        self.thread = threading.Thread(target=self._run, args=(inputs,), name="camera-later", daemon=True)
        self.thread.start()

    def _run(self, inputs: Inputs) -> None:
        try:
            later(self.cam, inputs, self.said)
        except Exception as e:  # noqa: BLE001 - a check beside the measurement: the measurement is kept
            self.cam.later = {"checked": False}
            self.said.append(
                f"camera check of the rest of the clip not done ({type(e).__name__}: {e}); please report this"
            )

    def join(self, warnings: list[str], robust: dict) -> None:
        self.thread.join()
        warnings.extend(self.said)
        robust["camera"] = self.cam.facts()


def _registers(project: Project, inputs: Inputs) -> None:
    """Register the clip's first frames (whole, decoded again: the check's were read in the PIV's box) with the
    ``[stabilize]`` of ``project`` as the run would (run/frames.py); raises what :class:`Stabilizer` raises where
    it does not hold."""
    imgs = [f.image for f in inputs.source.head(N_FRAMES) if f.image is not None]
    if inputs.lens is not None:
        imgs = [inputs.lens.undistort(i) for i in imgs]
    stab = make_stabilizer(project, inputs, imgs[0])
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
    """The camera moved and the run could not stabilise, in the first frames or later in the clip: a doubtful
    verdict (a good grade becomes doubtful)."""
    if quality is None or not facts:
        return
    late = facts.get("later") or {}
    if facts.get("moved") and not facts.get("stabilized"):
        why = (
            f"the camera moved up to {facts['max_shift_px']:.2f} px in the first frames and the frames could not "
            "be registered on the GCPs: the velocities carry the camera's motion; set [stabilize]"
        )
        value, limit = facts["max_shift_px"], facts["threshold_px"]
    elif late.get("moved"):
        why = (
            f"the camera moved up to {late['max_shift_px']:.2f} px from {late['from_s']:.2f} s on, after a still "
            "start: the velocities carry the camera's motion; set [stabilize] (the warning names the regions)"
        )
        value, limit = late["max_shift_px"], late["threshold_px"]
    else:
        return
    quality.reasons.append(Reason("camera_moved", "doubtful", why, value, limit))
    if quality.grade == "good":
        quality.grade = "doubtful"
