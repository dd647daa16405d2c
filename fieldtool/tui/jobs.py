"""Long work of the TUI, run in a worker thread: calibration, stabilisation check, PIV, the full run.

Each function takes a copy of the project (so edits made while it runs do not leak into it) and a
``Job`` that carries progress, the cancel flag and timing. They call the pipeline's stage functions
and never touch the UI.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from fieldtool.errors import Cancelled, FieldToolError, GeometryError, ParameterError
from fieldtool.processing import piv as piv_mod
from fieldtool.processing.calibration import calibrate_video, save_calibration
from fieldtool.project.model import Project, project_to_dict
from fieldtool.run import frames as run_frames
from fieldtool.run import piv_cache
from fieldtool.run.frames import Sized
from fieldtool.run.geometry import level_and_mapping, roi_and_mask
from fieldtool.run.inputs import load_inputs
from fieldtool.run.pipeline import run_project
from fieldtool.run.velocimetry import piv_params
from fieldtool.tui.piv_summary import water_median, water_nodes


class Job:
    """Progress and cancel flag of one run; read by the UI timer, written by the worker."""

    def __init__(self, name: str, title: str) -> None:
        self.name, self.title = name, title
        self.stage = ""
        self.done = 0
        self.total = 0
        self.t0 = time.monotonic()
        self._cancel = threading.Event()

    def progress(self, stage: str, done: int, total: int) -> None:
        self.stage, self.done, self.total = stage, done, total

    def progress2(self, stage: str):
        """A ``progress(done, total)`` callback for the given stage name."""
        return lambda done, total: self.progress(stage, done, total)

    def cancel(self) -> None:
        self._cancel.set()

    def cancelled(self) -> bool:
        return self._cancel.is_set()


def snapshot(project: Project) -> Project:
    """Deep copy of a project (``root`` kept)."""
    p = copy.deepcopy(project)
    p.root = Path(project.root)
    return p


def has_section(project: Project) -> bool:
    return np.asarray(project.section.points_px).shape == (2, 2)


# ---------------------------------------------------------------------------------------------


def run_full(project: Project, out_dir: Path, job: Job) -> dict:
    """Every step (pipeline.run_project), results written to ``out_dir``; returns the summary."""
    res = run_project(project, out_dir, progress=job.progress, cancel=job.cancelled)
    return res.summary()


# where the PIV-only run keeps its field, inside the output folder: not the pipeline's own PIV cache,
# because the discharge run's PIV has stages this run does not repeat (stationary-pattern removal,
# frame-gap planning), so its field must not be taken for the pipeline's
PREVIEW_DIR = "tui_piv"


def _piv_setup(project: Project, inputs):
    """What the PIV of ``project`` needs besides the frames, as pipeline.run_project sets it up:
    (mapping or None, roi, mask, params, speed limit in px/s or None, cache key or None).

    The key is the PIV cache's (``piv_cache.piv_key``) on every PIV input; it is None when a speed
    limit is set but the mapping cannot be built yet."""
    try:
        _, mapping = level_and_mapping(project, inputs)
    except FieldToolError:
        mapping = None
    roi, mask = roi_and_mask(project, inputs)
    params = piv_params(project)
    max_speed = None
    key = None
    if project.piv.max_velocity_ms is not None:
        if mapping is not None:
            x, y = piv_mod.grid(inputs.shape, params, roi)
            max_speed = project.piv.max_velocity_ms / mapping.scale_m_per_px(x, y)
            key = piv_cache.piv_key(project, max_speed)
    else:
        key = piv_cache.piv_key(project, None)
    return mapping, roi, mask, params, max_speed, key


def _preview(project: Project, res, mapping) -> dict:
    """The PIV step's summary of a field: {"inputs": project tables, "stats": {...}}; the median speed is
    that of the water nodes only (``piv_summary.water_nodes``: what moves), not of the banks."""
    speed = np.hypot(res.u, res.v)
    water = water_nodes(res.u, res.v, getattr(res, "valid_fraction", None))
    stats: dict[str, Any] = {
        "nodes": int(res.u.size),
        "water_nodes": int(water.sum()),
        "pairs": int(res.n_pairs or len(res.u_pairs)),
        "valid_fraction": float(np.nanmean(res.valid_fraction)),
        "median_speed_px_s": water_median(speed, water),
    }
    if mapping is not None:
        U, V = mapping.rectify_velocity(res.x, res.y, res.u, res.v)
        stats["median_speed_ms"] = water_median(np.hypot(U, V), water)
    stats["field"] = (res.x, res.y, res.u, res.v)
    stats["water"] = water
    return {"inputs": project_to_dict(project), "stats": stats}


def run_piv_only(project: Project, job: Job, out_dir: Path | None = None) -> dict:
    """PIV on the project's clip (before a section of interest exists): field statistics.

    The level and mapping are used when they can be computed (speed limit, m/s statistics). The
    field is saved at once under ``out_dir/tui_piv`` (the PIV cache's format and key): quitting before
    a section exists loses nothing, the PIV step shows it again when the project is reopened."""
    job.progress("inputs", 0, 0)
    inputs = load_inputs(project)
    mapping, roi, mask, params, max_speed, key = _piv_setup(project, inputs)
    stab: dict = {}
    stream = run_frames.working_frames(
        project, inputs, job.cancelled, None, stab if project.stabilize.enabled else None, job.progress
    )
    n_expected = inputs.source.estimated_count()
    # with the count: the same pair plan as the discharge run
    frames: Iterable[tuple[float, np.ndarray]] = Sized(stream, n_expected) if n_expected else stream
    res = piv_mod.analyze(frames, params, roi=roi, mask=mask, max_speed_px_s=max_speed, cancel=job.cancelled)
    if out_dir is not None and key is not None:
        folder = Path(out_dir) / PREVIEW_DIR
        folder.mkdir(parents=True, exist_ok=True)
        piv_cache.save(folder, key, res, stab or None)
    return _preview(project, res, mapping)


def cached_piv(project: Project, inputs, out_dir: Path) -> dict | None:
    """The PIV step's summary of the field a PIV-only run saved in ``out_dir`` for the project's
    current PIV inputs, or None (none, other inputs, unreadable)."""
    try:
        mapping, _, _, _, _, key = _piv_setup(project, inputs)
    except FieldToolError:
        return None
    if key is None:
        return None
    hit = piv_cache.load(Path(out_dir) / PREVIEW_DIR, key)
    if hit is None:
        return None
    return _preview(project, hit[0], mapping)


def run_calibration(project: Project, job: Job) -> dict:
    """Calibrate from the checkerboard video and write the lens file named by calibration.path."""
    c = project.calibration
    if not c.path:
        raise ParameterError("calibration.path: give the file name the calibration is saved as")
    model = calibrate_video(
        project.resolve(c.checkerboard_video),
        tuple(int(v) for v in c.corners),
        c.square_mm,
        c.n_frames,
        progress=job.progress2("checkerboard frames"),
        cancel=job.cancelled,
    )
    save_calibration(model, project.resolve(c.path))
    return {
        "inputs": project_to_dict(project)["calibration"],
        "rms_px": model.rms_px,
        "fov_deg": model.fov_deg,
        "views": len(model.frames_used),
    }


def run_stabilization(project: Project, job: Job) -> dict:
    """Register the clip on its first frame (filters off) and report the residual motion."""
    p = snapshot(project)
    p.filters = []
    inputs = load_inputs(p)
    report: dict = {}
    for _ in run_frames.working_frames(p, inputs, job.cancelled, None, report, job.progress, stage="stabilising"):
        pass
    if not report:
        raise GeometryError("stabilize: the clip gave no frame to register")
    return report


def describe_error(title: str, error: BaseException | None, took: float) -> tuple[str, bool]:
    """Text for a run that did not finish, and whether it is an error (a cancel is not)."""
    if isinstance(error, Cancelled) or error is None:
        return f"{title} cancelled after {took:.1f} s; nothing was changed", False
    if isinstance(error, FieldToolError):
        return f"{title} stopped: {error}", True
    return f"{title} failed (internal error, please report): {type(error).__name__}: {error}", True
