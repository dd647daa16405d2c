"""Run the steps of a Project in order (thesis figure 9.1) and write the results.

Stages: inputs (cross-section, clip, lens) -> water level -> orthorectification -> ROI/masks ->
frames (undistort, stabilise, filters) streamed into PIV -> rectified field -> discharge -> files.

``run_project`` takes ``progress(stage, done, total)``, ``cancel() -> bool`` and an ``Observer``
(the rerun logger is one) and never prints. Each stage is also a public function so the TUI can run
a step on its own.
"""

from __future__ import annotations

import importlib
import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from fieldtool import __version__
from fieldtool.run import piv_cache, stiv_stage
from fieldtool.errors import Cancelled, FieldToolError, GeometryError, InputFileError, ParameterError
from fieldtool.processing import cross_section as xs
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho
from fieldtool.processing.frames import FrameSource, read_color_frame
from fieldtool.project.model import Project, atomic_write_bytes, project_to_dict

Progress = Callable[[str, int, int], None]


class Observer:
    """Receives what the pipeline computes, as it computes it. Every method is optional; an
    observer must never raise (the pipeline guards it anyway and reports a warning)."""

    def stage(self, name: str) -> None: ...

    def frame(self, index: int, t_s: float, raw: np.ndarray, filtered: np.ndarray) -> None: ...

    def geometry(self, pair_discharge: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], float]) -> None:
        """Called once before PIV: ``pair_discharge(x, y, u_px_s, v_px_s) -> m³/s`` for live discharge."""

    def pair(self, i: int, t_s: float, x: np.ndarray, y: np.ndarray, u_px_s: np.ndarray, v_px_s: np.ndarray,
             valid: np.ndarray) -> None: ...

    def result(self, result: "RunResult") -> None: ...

    def warning(self, message: str) -> None: ...


class _Guarded:
    """Calls an observer, turning its failures into warnings: logging never fails a run."""

    def __init__(self, obs: Observer | None, warnings: list[str]):
        self.obs, self.warnings, self.failed = obs, warnings, False

    def __call__(self, method: str, *args) -> None:
        if self.obs is None or self.failed:
            return
        try:
            getattr(self.obs, method)(*args)
        except Exception as e:  # noqa: BLE001 - a logger must not break a measurement
            self.failed = True
            self.warnings.append(f"live logging stopped: {type(e).__name__}: {e}")


@dataclass
class Inputs:
    """Loaded inputs: cross-section, clip, optional lens model, and the working first frame."""

    cross_section: xs.CrossSection
    source: FrameSource
    lens: object | None  # calibration.LensModel
    first_color: np.ndarray  # BGR raw first frame of the range

    def to_working(self, pts) -> np.ndarray:
        """Raw-frame pixels -> working-image pixels (undistorted when a lens model is given)."""
        p = np.asarray(pts, float).reshape(-1, 2)
        return self.lens.undistort_points(p) if self.lens is not None and len(p) else p

    @property
    def shape(self) -> tuple[int, int]:
        return self.source.shape


@dataclass
class RunResult:
    """Everything one run produced. ``summary()`` is what ``result.json`` holds."""

    discharge: dq.DischargeResult
    q_pairs: np.ndarray
    level: object  # water_level.LevelResult
    mapping: ortho.OrthoMapping
    piv: object  # piv.PivResult
    section: dq.SectionGeometry
    world_u: np.ndarray
    world_v: np.ndarray
    out_dir: Path | None
    files: dict[str, str] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    stabilization: dict | None = None
    project: dict = field(default_factory=dict)
    piv_reused: bool = False  # the PIV field came from the output folder's piv_cache.npz
    stiv: dict | None = None  # STIV beside PIV per subsection (stiv_stage.finish); None when [stiv] enabled = false
    uncertainty: object | None = None  # processing.uncertainty.McResult
    quality: object | None = None  # processing.quality.Quality
    sections: list = field(default_factory=list)  # several sections: the main one first (fieldtool.run.sections)
    robust: dict | None = None  # facts of the robust stages (processing/surface.py, robust.py, planning.py)
    piv_fast: dict | None = None  # region box and pair sampling of the fast path (see piv_region / run_piv_fast)
    video: dict = field(default_factory=dict)  # the clip's metadata (records.video_meta.video_info)
    prerendered: object | None = None  # plots.prerender.Prerender: figures drawn during the PIV

    def summary(self) -> dict:
        d = self.discharge
        qp = self.q_pairs[np.isfinite(self.q_pairs)]
        lv = self.level
        return {
            "discharge_m3s": d.discharge_m3s,
            "discharge_ci95_m3s": (list(self.uncertainty.ci95_m3s) if self.uncertainty is not None
                                   and np.all(np.isfinite(self.uncertainty.ci95_m3s)) else None),
            "uncertainty": self.uncertainty.to_dict() if self.uncertainty is not None else None,
            "quality": self.quality.to_dict() if self.quality is not None else None,
            "sections": self.sections or None,
            "sections_summary": _sections_summary(self.sections),
            # spread of the discharges of single frame pairs (the sampled pairs, n_pairs_with_vectors of them):
            # not an interval of Q, which averages every pair (see discharge_ci95_m3s)
            "discharge_p05_m3s": float(np.percentile(qp, 5)) if len(qp) else None,
            "discharge_p95_m3s": float(np.percentile(qp, 95)) if len(qp) else None,
            "discharge_pairs_median_m3s": float(np.median(qp)) if len(qp) else None,
            "water_level_m": d.water_level_m,
            "water_level_method": lv.method,
            "water_level_uncertainty_m": lv.uncertainty_m,
            "wetted_area_m2": d.wetted_area_m2,
            "wetted_width_m": d.wetted_width_m,
            "mean_velocity_ms": d.mean_velocity_ms,
            "alpha": d.alpha,
            "alpha_default": d.alpha_default,
            "section_length_m": d.section_length_m,
            "n_pairs": int(getattr(self.piv, "n_pairs", 0) or len(self.q_pairs)),
            "n_pairs_with_vectors": int(len(self.q_pairs)),
            "valid_fraction_mean": float(np.nanmean(self.piv.valid_fraction)),
            "subsections_filled": int(d.velocity_filled.sum()),
            "ortho_method": self.mapping.method,
            "ortho_residual_m": self.mapping.residual_m,
            "ortho_details": self.mapping.details,
            "stabilization": self.stabilization,
            "piv_reused": self.piv_reused,
            "stiv": self.stiv,
            "robust": self.robust,
            **_fast_summary(self.piv_fast, int(getattr(self.piv, "n_pairs", 0) or len(self.q_pairs))),
            "video": self.video,
            "warnings": self.warnings + d.warnings,
            "timings_s": self.timings_s,
            "files": self.files,
            "fieldtool_version": __version__,
            "inputs": self.project,
        }


def _sections_summary(entries: list) -> dict | None:
    from fieldtool.run.sections import summarize

    return summarize(entries) if entries else None


# ---------------------------------------------------------------------------------------------
# stages


def load_cross_section(project: Project) -> xs.CrossSection:
    """The project's cross-section, from its shape or its file."""
    c = project.cross_section
    if c.shape:
        return xs.from_shape(c.shape, top_width_m=c.top_width_m, bottom_width_m=c.bottom_width_m, depth_m=c.depth_m,
                             left_station_m=c.left_station_m, bank_elevation_m=c.bank_elevation_m, points=c.points)
    if not c.path:
        raise ParameterError("cross_section.path: no cross-section given; set a CSV file or a shape")
    return xs.load_cross_section(project.resolve(c.path))


def load_inputs(project: Project) -> Inputs:
    """Cross-section, clip and lens model of a project, checked."""
    cs = load_cross_section(project)
    v = project.video
    if not v.path:
        raise ParameterError("video.path: no video given; set the clip to analyse")
    from fieldtool.project.validation import path_problem

    msg = path_problem(project.resolve(v.path), "video.path", kind="video")  # a FIFO must not block the open
    if msg:
        raise InputFileError(f"video.path: {msg}")
    src = FrameSource(project.resolve(v.path), v.start_s, v.end_s, v.step, v.frame_interval_s)
    lens = None
    if project.calibration.path:
        from fieldtool.processing.calibration import load_calibration

        lens = load_calibration(project.resolve(project.calibration.path))
    first = read_color_frame(project.resolve(v.path), v.start_s, v.frame_interval_s)
    return Inputs(cs, src, lens, first)


def detect_waterline(project: Project, inputs: Inputs, mapping: ortho.OrthoMapping | None = None) -> dict:
    """Water edges found along the search line in the clip's first frames (processing.waterline): the
    project's ``water_level.search_line_px``, else the section's points lengthened by 40 % each way; with a
    ``mapping``, also along 2 lines each side of it, ``water_level.search_spacing_m`` apart on the water."""
    from fieldtool.processing import waterline

    wl = project.water_level
    if wl.search_line_px:
        line = inputs.to_working(wl.search_line_px)
        if line.shape != (2, 2):
            raise ParameterError("water_level.search_line_px: give two [x, y] pixel points, one on each bank")
    else:
        sec = np.asarray(project.section.points_px, float)
        if sec.shape != (2, 2):
            raise ParameterError("water_level.search_line_px: draw a line from bank to bank across the river "
                                 "(or pick the section's water edges, which it extends)")
        line = waterline.extend_line(*inputs.to_working(sec), 0.4, inputs.shape)
    lines = (waterline.parallel_lines(line, mapping, wl.search_spacing_m, 2, inputs.shape) if mapping is not None
             else [(0.0, line)])
    frames = (inputs.lens.undistort(f.image) if inputs.lens is not None else f.image for f in inputs.source)
    return waterline.detect_water_edges(frames, lines)


def compute_level(project: Project, inputs: Inputs, mapping: ortho.OrthoMapping | None):
    """Water level by the project's method (see processing.water_level)."""
    from fieldtool.processing.water_level import compute_level as _compute

    detected = detect_waterline(project, inputs, mapping) if project.water_level.method == "waterline" else None
    sec = project.section
    station_of = None  # with a surveyed station of the section's first point, each edge gives a level too
    if detected is not None and sec.station_offset_m is not None and np.shape(sec.points_px) == (2, 2):
        from fieldtool.processing.waterline import station_function

        station_of = station_function(inputs.to_working(sec.points_px), mapping, sec.station_offset_m)
    fov = inputs.lens.fov_deg() if inputs.lens is not None else None
    return _compute(project.water_level, inputs.cross_section, root=project.root, mapping=mapping, fov_deg=fov,
                    points_transform=inputs.to_working if inputs.lens is not None else None,
                    image_undistort=inputs.lens.undistort_points_in if inputs.lens is not None else None,
                    detected=detected, station_of=station_of)


def build_mapping(project: Project, inputs: Inputs, level_m: float | None) -> ortho.OrthoMapping:
    """Image -> water-plane mapping by the project's ortho method. ``level_m`` is needed for
    method 'none' (scale from the wetted width) and 'pose' (plane at the level)."""
    o = project.ortho
    shape = inputs.shape
    if o.method == "distances":
        raw = np.asarray(o.gcp_px, float)
        if raw.shape != (4, 2):
            raise ParameterError("ortho.gcp_px: give exactly four [x, y] pixel points P1..P4 for method = distances")
        ortho.check_in_frame(raw, shape, "ortho.gcp_px")
        return ortho.from_distances(inputs.to_working(raw), o.distances_m, max_residual_m=o.max_residual_m,
                                    accept_residual=o.accept_residual, frame_shape=shape)
    if o.method == "two_points":
        raw = np.asarray(o.gcp_px, float)
        if raw.shape != (2, 2):
            raise ParameterError("ortho.gcp_px: give exactly two [x, y] pixel points P1, P2 for method = two_points")
        ortho.check_in_frame(raw, shape, "ortho.gcp_px")
        return ortho.from_two_points(inputs.to_working(raw), o.distances_m[0] if len(o.distances_m) == 1 else None,
                                     o.gcp_world_m or None)
    if o.method == "world":
        raw = np.asarray(o.gcp_px, float)
        ortho.check_in_frame(raw.reshape(-1, 2), shape, "ortho.gcp_px")
        m = ortho.from_world_points(inputs.to_working(raw), o.gcp_world_m)
        ortho.check_gcp_residuals(m, inputs.to_working(raw), o.max_residual_m, o.accept_residual)
        return m
    if o.method == "pose":
        from fieldtool.processing import pose

        if level_m is None:
            raise ParameterError("ortho.method = pose needs the water level first")
        raw = np.asarray(o.gcp_px, float)
        world = np.asarray(o.gcp_world_m, float)
        lens_fit = None
        if inputs.lens is None:
            if not o.fit_lens:
                raise ParameterError("ortho.method = pose needs the camera intrinsics: set calibration.path, or set "
                                     "ortho.fit_lens = true to fit focal length and k1 from 8+ GCPs")
            from fieldtool.processing.calibration import LensModel

            h, w = shape
            K, dist, p, lens_fit = pose.fit_lens(raw, world, (w, h))
            inputs.lens = LensModel(K, dist, (w, h), rms_px=lens_fit["rms_px"])  # frames are undistorted with it
        else:
            p = pose.solve_pose(raw, world, inputs.lens.camera_matrix, inputs.lens.dist_coeffs)
        H = pose.plane_homography(p, level_m)
        # residual in metres: each GCP's ray met on the horizontal plane at its own elevation
        und = inputs.to_working(raw)
        miss = [np.hypot(*(ortho._apply(pose.plane_homography(p, z), und[i:i + 1])[0] - world[i, :2]))
                for i, z in enumerate(world[:, 2])]
        details = {"reprojection_rms_px": p.rms_px, "gcp_residual_m": [float(m) for m in miss],
                   "gcp_reprojection_px": [float(r) for r in p.reprojection_px]}
        if lens_fit is not None:
            details["lens_from_gcps"] = lens_fit
        m = ortho.from_homography(H, "pose", float(np.sqrt(np.mean(np.square(miss)))), world[:, :2], details)
        ortho.check_gcp_residuals(m, und, o.max_residual_m, o.accept_residual)
        return m
    if o.method == "none":
        if level_m is None:
            raise ParameterError("ortho.method = none takes the image scale from the wetted width: the water level is needed first")
        pts = inputs.to_working(project.section.points_px)
        if pts.shape != (2, 2):
            raise ParameterError("section.points_px: give the two water edges; without GCPs they set the image scale")
        # the picked points are the OUTER water edges, so the scale is their distance on the cross-section,
        # not the wetted width (which leaves out islands: -8.3 % with a 1 m island in 12 m)
        length_px = float(np.hypot(*(pts[1] - pts[0])))
        left, right = inputs.cross_section.water_edges(level_m)
        return ortho.from_scale((right - left) / length_px)
    raise ParameterError(f"ortho.method: {o.method!r} is not one of distances, world, pose, two_points, none")


def build_section(project: Project, inputs: Inputs, level_m: float, mapping: ortho.OrthoMapping,
                  points_px=None) -> dq.SectionGeometry:
    """The section of interest (raw-frame ``points_px``, default the project's), checked against the water
    edges of the cross-section at ``level_m`` (see processing.discharge.check_section)."""
    sec = project.section
    pts = sec.points_px if points_px is None else points_px
    if np.asarray(pts).shape == (2, 2):  # raw-frame pixels, checked before undistortion
        ortho.check_in_frame(np.asarray(pts, float), inputs.shape, "section.points_px")
    geom = dq.section_geometry(inputs.to_working(pts) if len(pts) else pts, mapping, inputs.cross_section,
                               level_m, sec.n_sub, sec.station_offset_m,
                               footprint_px=dq.window_reach_px(project.piv.window_px))
    dq.check_section(geom, inputs.cross_section, level_m, sec.min_length_fraction, sec.edge_tolerance_m)
    return geom


def level_and_mapping(project: Project, inputs: Inputs):
    """Water level and image -> water-plane mapping, in the order the methods need: the image method
    measures the level on the mapping; every other method gives the level the mapping may need."""
    if project.water_level.method in ("image", "waterline"):
        mapping = build_mapping(project, inputs, None)
        level = compute_level(project, inputs, mapping)
    else:
        level = compute_level(project, inputs, None)
        mapping = build_mapping(project, inputs, level.level_m)
    inputs.cross_section.check_level(level.level_m)
    return level, mapping


def roi_and_mask(project: Project, inputs: Inputs) -> tuple[tuple[int, int, int, int] | None, np.ndarray | None]:
    """ROI (x0, y0, x1, y1) and invalid-area mask in working-image pixels."""
    h, w = inputs.shape
    roi = None
    if project.roi.rect_px:
        r = project.roi.rect_px
        if len(r) != 4:
            raise ParameterError("roi.rect_px: give [x0, y0, x1, y1] in pixels")
        corners = inputs.to_working([[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]])
        x0, y0 = np.floor(corners.min(axis=0)).astype(int)
        x1, y1 = np.ceil(corners.max(axis=0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 - x0 < 8 or y1 - y0 < 8:
            raise GeometryError(f"roi.rect_px: {r} leaves no usable area inside the {w}x{h} frame")
        roi = (int(x0), int(y0), int(x1), int(y1))
    mask = None
    if project.roi.masks_px:
        from fieldtool.processing.masks import rasterize

        polys = [inputs.to_working(p).tolist() if len(p) >= 3 else p for p in project.roi.masks_px]
        mask = rasterize((h, w), polys)
    return roi, mask


def working_frames(project: Project, inputs: Inputs, cancel: Callable[[], bool] | None = None,
                   observer: _Guarded | None = None, stab_report: dict | None = None,
                   progress: Progress | None = None, stage: str = "frames",
                   want: Callable[[int], bool] | None = None, raw: bool = False) -> Iterator[tuple[float, np.ndarray]]:
    """Stream (t_s, float32 working frame): undistorted, stabilised, filtered.

    ``raw``: without filters, the frames keep the decoder's uint8 (for consumers that convert only what they
    read: the standardisation's box, STIV's lines).

    ``want(k)``: frames at stream positions k that fail it come as (t_s, None), decoded past but not converted
    (the fast path's rounds need only their own pairs' frames). Ignored with stabilisation, which tracks every
    frame, and with a filter stack marked ``temporal``."""
    from fieldtool.processing.filters import FilterStack

    # filters work inside the ROI only (thesis 9.2.7): banks and sky do not set their statistics
    stack = FilterStack.from_config(project.filters, roi=roi_and_mask(project, inputs)[0]) if project.filters else None
    if project.stabilize.enabled or getattr(stack, "temporal", False):
        want = None
    stabilizer = None
    total = inputs.source.estimated_count()

    def corrected() -> Iterator[tuple[int, float, np.ndarray]]:
        nonlocal stabilizer
        for fr in (inputs.source if want is None else inputs.source.iter_wanted(want)):
            img = fr.image
            if img is None:
                yield fr.index, fr.t_s, None
                continue
            if inputs.lens is not None:
                img = inputs.lens.undistort(img)
            if project.stabilize.enabled:
                if stabilizer is None:
                    from fieldtool.processing.stabilize import Stabilizer

                    st = project.stabilize
                    regions = [inputs.to_working([[r[0], r[1]], [r[2], r[3]]]).ravel().tolist() for r in st.regions_px]
                    poly = inputs.to_working(st.water_polygon_px).tolist() if st.water_polygon_px else None
                    stabilizer = Stabilizer(img, regions_px=regions or None, water_polygon_px=poly, model=st.model,
                                            max_drift_px=st.max_drift_px)
                else:
                    img = stabilizer.register(img)
            yield fr.index, fr.t_s, img

    if stack is not None and stack.needs_prepass:
        want, want_later = None, want
        stack.prepass(img for _, _, img in corrected())
        want = want_later
        stabilizer = None  # registered again on the second pass, identically
    log_every = max(1, total // 20) if total else 10
    for k, (idx, t, img) in enumerate(corrected()):
        if cancel is not None and cancel():
            raise Cancelled("cancelled by the user")
        if img is None:
            if progress is not None:
                progress(stage, k + 1, total)
            yield t, None
            continue
        out = stack.apply(img) if stack is not None else img if raw else img.astype(np.float32)
        if observer is not None and k % log_every == 0:
            observer("frame", idx, t, img, out)
        if progress is not None:
            progress(stage, k + 1, total)
        yield t, out
    if stab_report is not None and stabilizer is not None:
        stab_report.update(stabilizer.report())


def _count_identical(frames: Iterator[tuple[float, np.ndarray]], stats: dict) -> Iterator[tuple[float, np.ndarray]]:
    """Pass the frames through, counting consecutive frames that are identical (duplicates, a still image)."""
    prev = None
    n = same = 0
    for t, img in frames:
        if img is None:  # a frame the fast path did not decode (working_frames(want=...))
            yield t, img
            continue
        if prev is not None:
            n += 1
            sub = img[::4, ::4]
            if float(np.max(np.abs(sub - prev))) < 0.5:
                same += 1
        prev = img[::4, ::4].astype(np.float32, copy=True)
        stats["pairs"], stats["identical"] = n, same
        yield t, img


class _Sized:
    """A frame stream with the count the container claims (a plan, not a promise: it may end sooner)."""

    def __init__(self, frames: Iterator, n: int):
        self.frames, self.n = frames, n

    def __iter__(self) -> Iterator:
        return iter(self.frames)

    def __len__(self) -> int:
        return self.n


def piv_params(project: Project):
    from fieldtool.processing.piv import PivParams

    p = project.piv
    return PivParams(window_px=p.window_px, overlap_px=p.overlap_px, search_px=p.search_px, passes=p.passes,
                     snr_min=p.snr_min, averaging=p.averaging, median_threshold=p.median_threshold,
                     std_threshold=p.std_threshold, min_valid_fraction=p.min_valid_fraction, engine=p.engine,
                     frame_gap=p.frame_gap or 1, remove_zero_peak=p.remove_zero_peak)


def piv_region(project: Project, inputs: Inputs, params, roi, segments) -> tuple[int, int, int, int] | None:
    """The box PIV correlates (working-image px), by ``[piv] region``: ``section`` a band around the section
    segment(s) (list of (2, 2) working-image points) within the ROI, ``roi`` the ROI (None = whole frame),
    ``full`` the whole frame (None)."""
    from fieldtool.processing import piv_fast

    region = project.piv.region
    if region not in piv_fast.REGIONS:
        raise ParameterError(f"piv.region: {region!r} is not one of {', '.join(piv_fast.REGIONS)}")
    if region == "full":
        return None
    if region == "roi":
        return roi
    margin = piv_fast.band_margin_px(params.window_px, params.overlap_px, params.passes, params.search_px)
    w0 = params.window_px * 2 ** (params.passes - 1)
    side = max(w0, int(params.search_px or 0)) + 2 * (params.window_px - params.overlap_px) * 2 ** (params.passes - 1)
    return piv_fast.section_band(inputs.shape, segments, margin, roi, min_side_px=side)


def run_piv_fast(make_frames, n_pairs: int, gap: int, params, roi, mask, max_speed, cancel, on_pair, pair_q,
                 rel_ci: float, min_pairs: int, drain_first: bool = False, near=None, first_guess=None):
    """PIV with pairs added until the discharge has converged (``processing.piv_fast.converge``), each round's
    frames read by a background thread (``make_frames`` may hand one already reading). ``drain_first``: the
    first round's stream is read to its end (STIV samples its lines from it). Returns (PivResult, dict of
    pairs_used, converged, ...)."""
    from dataclasses import asdict

    from fieldtool.processing import piv as piv_mod
    from fieldtool.processing import piv_fast

    if not (isinstance(rel_ci, (int, float)) and np.isfinite(rel_ci) and rel_ci > 0):
        raise ParameterError(f"piv.converge_rel_ci: {rel_ci!r} must be a number above 0 (0.005 = +-0.5 %)")
    if isinstance(min_pairs, bool) or not isinstance(min_pairs, int) or min_pairs < 2:
        raise ParameterError(f"piv.min_pairs: {min_pairs!r} must be a whole number of 2 or more (30 is usual)")

    def run(frames, select, carry):
        reader = frames if isinstance(frames, (piv_fast.prefetch, piv_fast.Prefetched)) else piv_fast.prefetch(frames)
        try:
            res = piv_mod.analyze(reader, params, roi=roi, mask=mask, max_speed_px_s=max_speed, cancel=cancel,
                                  on_pair=on_pair, select=select, carry=carry, near=near, first_guess=first_guess)
            if carry is None and drain_first:
                for _ in reader:
                    pass
            return res
        finally:
            reader.close()

    res, conv, _ = piv_fast.converge(make_frames, n_pairs, run, pair_q, rel_ci=rel_ci, min_pairs=min_pairs,
                                     frame_gap=gap)
    return res, asdict(conv)


def _fast_summary(fast: dict | None, n_pairs: int) -> dict:
    """result.json keys of the fast path: pairs_used, converged, piv_region."""
    fast = fast or {}
    out = {"pairs_used": int(fast.get("pairs_used", n_pairs)), "converged": fast.get("converged")}
    if fast:
        out["piv_sampling"] = {k: fast.get(k) for k in ("pairs_total", "rel_ci", "threshold", "min_pairs", "rounds")
                               if k in fast}
        out["piv_region"] = {k: fast.get(k) for k in ("region", "box_px", "roi_px")}
    return out


# ---------------------------------------------------------------------------------------------
# the whole run


def run_project(project: Project, out_dir: Path | str | None = None, *, progress: Progress | None = None,
                cancel: Callable[[], bool] | None = None, observer: Observer | None = None) -> RunResult:
    """Run every step of ``project``; write the results to ``out_dir`` when given. The figure process the run
    draws its figures in (``plots.prerender``) ends with the run, whether it succeeds, fails or is cancelled."""
    import contextlib

    with contextlib.ExitStack() as ends:
        return _run_project(project, out_dir, progress, cancel, observer, ends)


def _run_project(project: Project, out_dir: Path | str | None, progress: Progress | None,
                 cancel: Callable[[], bool] | None, observer: Observer | None, ends) -> RunResult:
    """:func:`run_project`; ``ends`` (a contextlib.ExitStack) takes what must be closed when the run ends."""
    from fieldtool.processing import piv as piv_mod

    warnings: list[str] = []
    obs = _Guarded(observer, warnings)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t0
        now = time.perf_counter()
        timings[name] = round(now - t0, 3)
        t0 = now

    if out_dir is not None:
        from fieldtool.plots import prerender

        prerender.start()  # the figure process (plots.prerender), forked before this run starts any thread
        # scipy.spatial (~0.1 s, the NetCDF grid) is imported while the PIV waits for its frames; so is
        # matplotlib (~0.5 s) where no figure process draws the figures
        modules = ("scipy.spatial",) if prerender.can_fork() else ("fieldtool.plots.discharge", "scipy.spatial")
        threading.Thread(target=lambda: [importlib.import_module(m) for m in modules], daemon=True).start()
    from fieldtool.project.validation import check

    warnings += [str(w) for w in check(project)]  # every key, before any step
    from fieldtool.run.sections import parse as parse_sections

    extra_sections = parse_sections(project)
    obs("stage", "inputs")
    from fieldtool.writers import check as check_outputs

    check_outputs(project)  # a wrong ortho.crs_epsg stops the run before any work
    inputs = load_inputs(project)
    lap("inputs")

    obs("stage", "water_level")
    level, mapping = level_and_mapping(project, inputs)
    cs = inputs.cross_section
    lap("level_and_ortho")

    sec = project.section
    geom = build_section(project, inputs, level.level_m, mapping)
    roi, mask = roi_and_mask(project, inputs)
    stiv_run = stiv_stage.start(project, mapping, geom, inputs.shape, roi, mask)

    params = piv_params(project)
    # stationary-pattern removal standardises each pixel over a window of frames: a clip shorter than that
    # window (e.g. 1 s of natural texture) would lose its own texture to the window's mean
    from fieldtool.processing.surface import HALF_WINDOW

    n_clip = inputs.source.estimated_count() or 0
    standardize = project.piv.remove_stationary and (n_clip == 0 or n_clip >= 2 * HALF_WINDOW + 1)
    if project.piv.remove_stationary and not standardize:
        warnings.append(f"piv.remove_stationary: the clip has {n_clip} frames, fewer than the {2 * HALF_WINDOW + 1} its "
                        "time window needs; glints and other patterns fixed in the image are not removed")
    from fieldtool.run import clip_check, unmeasured  # issue 23: gates from the clip's noise and contrast

    clip = clip_check.check(inputs, roi, n_clip, params, mask, standardize, project.piv.frame_gap)
    params = clip.params(params, standardize)
    roi_user = roi
    segments = [geom.p_img] + [inputs.to_working(s.points_px) for s in extra_sections if len(s.points_px)]
    roi = piv_region(project, inputs, params, roi, segments)
    near = None
    if project.piv.region == "section" and roi is not None:  # in the band's box, only the nodes near the sections
        from fieldtool.processing.piv_fast import node_reach_px

        near = ([np.asarray(sg, float)[:2] for sg in segments],
                node_reach_px(params.window_px, params.overlap_px, params.passes))
    x, y = piv_mod.grid(inputs.shape, params, roi)
    max_speed = None
    if project.piv.max_velocity_ms is not None:
        max_speed = project.piv.max_velocity_ms / mapping.scale_m_per_px(x, y)

    def pair_q_fn(g: dq.SectionGeometry, cs_g: xs.CrossSection | None = None) -> Callable[..., float]:
        """Discharge of one pixel-velocity field (px/s) on the section ``g`` (cross-section ``cs_g``, default
        the project's)."""
        cs_g = cs if cs_g is None else cs_g
        area, _ = dq.subsection_areas(g, cs_g, level.level_m)
        law = dq.manning_factors(cs_g, level.level_m, g.station_edges)
        alpha = dq.resolve_alpha(sec.alpha, cs_g, level.level_m)

        def q(xx, yy, u, v) -> float:
            Uw, Vw = mapping.rectify_velocity(xx, yy, u, v)
            return dq.pair_discharge(g, area, law, alpha, xx, yy, Uw, Vw)

        return q

    obs("geometry", pair_q_fn(geom))
    obs("stage", "piv")
    prerendered = None
    if out_dir is not None:  # the figures of the inputs are drawn in the figure process during the PIV
        from fieldtool.plots.prerender import Prerender

        prerendered = Prerender(project, inputs, level, mapping)
        ends.callback(prerendered.close)
    stab: dict = {}
    frame_stats: dict = {}
    surface_stats = None
    plan = None
    if standardize:
        from fieldtool.processing.surface import SurfaceStats

        surface_stats = SurfaceStats()

    def on_pair(i, t, xx, yy, u, v, valid):
        obs("pair", i, t, xx, yy, u, v, valid)

    # the pixel-space field is reused when only the mapping, level, section or alpha changed (not while
    # streaming to an observer, who wants to see the frames and pairs)
    cache_dir = Path(out_dir) if out_dir is not None and observer is None else None
    key = piv_cache.piv_key(project, max_speed, roi, near) if cache_dir is not None else ""
    cached = piv_cache.load(cache_dir, key, with_extra=True) if cache_dir is not None else None
    fast = {"region": project.piv.region, "box_px": None if roi is None else list(roi),
            "roi_px": None if roi_user is None else list(roi_user)}
    decoded: list[float] = []
    from dataclasses import replace as _replace

    from fieldtool.processing import planning

    def piv_stream(want=None, tap: bool = False):
        """The frames PIV reads: working frames, duplicate count, stationary-pattern removal (which needs every
        frame of its time window: then every frame is decoded and ``want`` only chooses the standardised frames
        that are built). ``tap``: STIV samples its lines from this stream."""
        want_std = want
        if standardize:  # every frame enters the standardisation's window; only the wanted ones are built
            want = None
        frames = working_frames(project, inputs, cancel, obs, stab if project.stabilize.enabled else None, progress,
                                want=want, raw=standardize)  # the standardisation converts its box only
        if tap and stiv_run is not None:  # STIV samples its lines from the same stream (one decode)
            frames = stiv_run.tap(frames)

        def tracked(it):
            for t, img in it:
                decoded[:] = [t]
                yield t, img

        frames = _count_identical(tracked(frames), frame_stats)
        if standardize:
            from fieldtool.processing import surface

            from fieldtool.processing.piv_fast import threaded

            surface_stats.frames = 0  # each round of the fast path standardises the clip again: count one pass
            frames = threaded(clip.before(frames))  # decoding (and STIV's sampling) in a thread of its own
            frames = surface.standardize(frames, roi, margin=max(64, params.search_px or 0), half=surface.HALF_WINDOW,
                                         shrink=clip.gates.shrink, stats=surface_stats, want=clip.std_want(want_std))
            frames = clip.after(frames, want_std)  # issue 23: weak clips' glint mask (before) and denoising
        return frames

    def plan_pairs(frames):
        nonlocal params, plan
        if project.piv.frame_gap is None:
            plan, frames = planning.first_look(frames, params, roi, mask)
            if params.search_px is not None or params.engine != "fieldtool":  # the user's search area, or an
                plan.guess = None  # engine that cannot move its windows: the wider search area instead
            if plan.guess is not None:
                plan.search_px = None  # the first pass starts from the look's field
            params = _replace(params, frame_gap=plan.frame_gap, search_px=params.search_px or plan.search_px)
            params = clip.gap(params)  # issue 23: denoised frames are paired beyond their averaging window
            plan.frame_gap = params.frame_gap
            if plan.frame_gap > 1 or plan.search_px or plan.guess is not None:
                warnings.append(
                    f"piv: from a first look at {plan.pairs_looked} pairs (slow nodes {plan.slow_px_per_frame:.1f}, "
                    f"fast nodes {plan.fast_px_per_frame:.1f} px per frame) pairs are {plan.frame_gap} frame(s) apart"
                    + (f" and the first pass searches {plan.search_px} px" if plan.search_px else "")
                    + (" and the first pass starts from the look's field" if plan.guess is not None else "")
                    + "; set piv.frame_gap (and piv.search_px) to choose yourself")
        else:
            plan = planning.Plan(frame_gap=int(project.piv.frame_gap), search_px=params.search_px, chosen="user")
        return frames

    n_exp = inputs.source.estimated_count()
    if cached is not None:
        res, stab_cached, extra = cached
        stab.update(stab_cached or {})
        extra = dict(extra or {})
        frame_stats.update(extra.pop("frame_stats", None) or {})  # identical frames are still a reason on reuse
        fast.update(extra)
    # pairs are added in rounds until the discharge converged (piv_fast.converge). With the stationary-pattern
    # removal every frame of its window must be read, so the first round is one streamed pass that STIV and
    # the first look share: its reader thread decodes and standardises every frame, but builds only the frames
    # of the round's pairs, spread over the clip; a further round (a new pass) only when not converged
    elif not project.piv.all_pairs and n_exp > 2:
        from fieldtool.processing.piv_fast import Prefetched, prefetch

        first = None
        if standardize:  # round 1 reads the stream the first look started; want is set when round 1 begins
            round1_want: list = [None]
            reader1 = prefetch(piv_stream(want=lambda k: round1_want[0] is None or round1_want[0](k), tap=True))
            first = plan_pairs(reader1)
        else:  # STIV then reads the clip by itself
            plan_pairs(piv_stream(want=lambda k: k <= planning.LOOK_PAIRS))  # the first look reads the first frames
        gap = max(1, int(params.frame_gap))

        def make_frames(want=None):
            nonlocal first
            if first is None:
                return piv_stream(want=want)
            round1_want[0] = want
            frames, first = Prefetched(first, reader1.close), None
            return frames

        try:
            if n_exp - gap >= 2:
                res, conv = run_piv_fast(make_frames, n_exp - gap, gap, params, roi, mask, max_speed, cancel, on_pair,
                                         pair_q_fn(geom), project.piv.converge_rel_ci, clip.min_pairs(project.piv.min_pairs),
                                         drain_first=standardize and stiv_run is not None, near=near,
                                         first_guess=plan.guess)
                fast.update(conv)
            else:
                frames = make_frames()
                try:
                    res = piv_mod.analyze(frames, params, roi=roi, mask=mask, max_speed_px_s=max_speed, cancel=cancel,
                                          on_pair=on_pair, near=near, first_guess=plan.guess)
                finally:
                    getattr(frames, "close", lambda: None)()
                fast.update(pairs_used=int(res.n_pairs or 0), converged=None)
        finally:  # round 1's reader thread stops even when the rounds never started (a key refused)
            if standardize:
                reader1.close()
        if cache_dir is not None:
            piv_cache.save(cache_dir, key, res, stab or None, {**fast, "frame_stats": frame_stats})
    else:
        from fieldtool.processing.piv_fast import prefetch

        frames = plan_pairs(piv_stream(tap=True))
        reader = prefetch(frames)
        frames = reader
        if n_exp:
            frames = _Sized(frames, n_exp)  # lets the ensemble plan which pairs get per-pair vectors
        try:
            res = piv_mod.analyze(frames, params, roi=roi, mask=mask, max_speed_px_s=max_speed,
                                  progress=None, cancel=cancel, on_pair=on_pair, near=near, first_guess=plan.guess)
        finally:
            reader.close()
        fast.update(pairs_used=int(res.n_pairs or 0), converged=None)
        if cache_dir is not None:
            piv_cache.save(cache_dir, key, res, stab or None, {**fast, "frame_stats": frame_stats})
        v, fps = project.video, getattr(getattr(inputs.source, "info", None), "fps", 0) or 0
        if v.end_s is not None and decoded and fps > 0 and decoded[0] < v.end_s - (v.step + 1) / fps:
            warnings.append(f"video.end_s: the clip decoded only up to {decoded[0]:.2f} s of the {v.end_s:g} s asked "
                            f"(its container claims more); the measurement covers {v.start_s:g}-{decoded[0]:.2f} s")
    stiv_stage.ensure_sampled(stiv_run, lambda: working_frames(project, inputs, cancel))
    lap("frames_and_piv")

    obs("stage", "discharge")
    U, V = mapping.rectify_velocity(res.x, res.y, res.u, res.v)
    v_sub = dq.subsection_velocity(geom, res.x, res.y, U, V)
    if unmeasured.nothing_measured(v_sub):  # issue 23: an unusable verdict (exit 3) with every file, not exit 2
        dres, qual = unmeasured.verdict(geom, cs, level.level_m, sec.alpha, clip.facts())
        result = RunResult(dres, np.zeros(0), level, mapping, res, geom, U, V, None, timings_s=timings,
                           warnings=warnings, stabilization=stab or None, project=project_to_dict(project),
                           piv_reused=cached is not None, quality=qual, robust={"plan": None, **clip.facts()},
                           piv_fast=fast)
        if out_dir is not None:
            write_outputs(result, project, inputs, Path(out_dir))
        obs("result", result)
        return result
    dres = dq.compute_discharge(geom, cs, level.level_m, v_sub, sec.alpha)
    if dres.discharge_m3s < 0:
        # P1/P2 picked right-to-left: swap them so P1 is the left edge, as the stations assume
        warnings.append("section.points_px were given right edge first; they were swapped (P1 must be the left "
                        "water edge looking downstream)")
        geom = build_section(project, inputs, level.level_m, mapping, np.asarray(sec.points_px, float)[::-1])
        geom.swapped = True
        v_sub = dq.subsection_velocity(geom, res.x, res.y, U, V)
        dres = dq.compute_discharge(geom, cs, level.level_m, v_sub, sec.alpha)
    robust_facts: dict = {"plan": plan.as_dict() if plan is not None else None}
    clip.annotate(robust_facts)  # issue 23: robust.noise, robust.contrast, robust.gates, robust.plan.preprocessing
    if surface_stats is not None:
        robust_facts["stationary_removed"] = {"frames": surface_stats.frames, "std_ref": surface_stats.std_ref,
                                              "specular_fraction": surface_stats.specular_fraction}
    zr = getattr(res, "zero_peak_removed", None)
    if zr is not None:
        robust_facts["zero_peak_removed_nodes"] = int(np.count_nonzero(zr))
    if project.piv.reject_upstream:
        from fieldtool.processing import robust

        v_clean, rejected = robust.reject_upstream(v_sub)
        robust_facts["upstream_rejected"] = [int(i) for i in np.flatnonzero(rejected)]
        if rejected.any():
            dres = dq.compute_discharge(geom, cs, level.level_m, v_clean, sec.alpha)
            warnings.append(f"{int(rejected.sum())} subsection(s) went upstream while the section goes downstream "
                            "(wind ripples, standing waves or glints); rejected and filled from their neighbours")
    stiv_block, dres = stiv_stage.finish(stiv_run, project, geom, cs, level.level_m, dres, res, U, V)
    from fieldtool.processing.robust import width_share

    robust_facts["filled_subsections"] = [int(i) for i in np.flatnonzero(dres.velocity_filled)]
    robust_facts["filled_width_share"] = width_share(dres.station_from, dres.station_to, dres.velocity_filled)
    def pairs_q(g: dq.SectionGeometry, cs_g: xs.CrossSection | None = None) -> np.ndarray:
        pair_q = pair_q_fn(g, cs_g)
        return np.array([pair_q(res.x, res.y, res.u_pairs[k], res.v_pairs[k]) for k in range(len(res.u_pairs))])

    q_pairs = pairs_q(geom)
    lap("discharge")
    if prerendered is not None:  # the velocity figures are drawn in the figure process during the Monte Carlo
        prerendered.results(inputs, dres, res, U, V, geom, mapping, cs)

    from fieldtool.run.assess import assess_run

    try:
        unc, qual = assess_run(project, inputs, level, mapping, geom, res, U, V, dres, q_pairs, frame_stats)
    except Exception as e:  # noqa: BLE001 - the discharge is kept; the missing verdict is said
        unc = qual = None
        warnings.append(f"uncertainty and quality not computed ({type(e).__name__}: {e}); please report this")
    stiv_stage.add_reason(qual, stiv_block)  # "PIV and STIV disagree ..." (doubtful)
    section_entries = []
    if extra_sections:
        from fieldtool.run import sections as secs

        main = {"name": "main", "points_px": np.asarray(sec.points_px, float).tolist(), "discharge_m3s": dres.discharge_m3s,
                "discharge_ci95_m3s": (list(unc.ci95_m3s) if unc is not None and np.all(np.isfinite(unc.ci95_m3s))
                                       else None), "grade": qual.grade if qual is not None else None,
                "wetted_area_m2": dres.wetted_area_m2, "wetted_width_m": dres.wetted_width_m,
                "mean_velocity_ms": dres.mean_velocity_ms, "subsections_filled": int(dres.velocity_filled.sum())}
        section_entries = [main] + [secs.measure(project, inputs, s, level, mapping, res, U, V, frame_stats, pairs_q)
                                    for s in extra_sections]
        for e in section_entries:
            if "error" in e:
                warnings.append(f"section {e['name']!r}: {e['error']}")
        summ = secs.summarize(section_entries)
        if qual is not None and summ is not None and summ["cv"] is not None \
                and summ["cv"] > project.quality.sections_cv_doubtful:
            from fieldtool.processing.quality import Reason

            qual.reasons.append(Reason("sections_disagree", "doubtful",
                                       f"the {summ['n']} sections' discharges differ by a coefficient of variation of "
                                       f"{100 * summ['cv']:.1f} % (quality.sections_cv_doubtful = "
                                       f"{100 * project.quality.sections_cv_doubtful:g} %)", summ["cv"],
                                       project.quality.sections_cv_doubtful))
            if qual.grade == "good":
                qual.grade = "doubtful"
    lap("uncertainty_and_quality")

    result = RunResult(dres, q_pairs, level, mapping, res, geom, U, V, None, timings_s=timings, warnings=warnings,
                       stabilization=stab or None, project=project_to_dict(project), piv_reused=cached is not None,
                       uncertainty=unc, quality=qual, sections=section_entries, robust=robust_facts,
                       stiv=stiv_block, piv_fast=fast, prerendered=prerendered)
    if out_dir is not None:
        write_outputs(result, project, inputs, Path(out_dir))
    obs("result", result)
    return result


# ---------------------------------------------------------------------------------------------
# outputs


def write_outputs(result: RunResult, project: Project, inputs: Inputs, out: Path) -> None:
    """result.json, subsections.csv, mean_field.npz/.npy and the PNG plots, each written atomically."""
    from fieldtool.run.outdir import Staging

    t0 = time.perf_counter()
    project_file_inside = out.exists() and out.resolve() in (project.root.resolve(), *project.root.resolve().parents)
    stage = Staging(out, in_place=project_file_inside)
    try:
        _write_outputs(result, inputs, stage.path)
        from fieldtool.writers import write_standard

        write_standard(result, project, inputs, stage.path)  # mean_field.nc, rectified.tif (with a CRS), video metadata
        _write_figures(result, inputs, stage.path)  # last: the figure process draws them meanwhile
        result.timings_s["outputs"] = round(time.perf_counter() - t0, 3)  # all but result.json itself
        _write_result_json(result, stage.path)
        stage.commit()
    except BaseException:
        stage.abort()
        raise
    result.out_dir = out


def _write_result_json(result: RunResult, out: Path) -> None:
    """result.json, strict JSON: a non-finite number is written as null and named in the warnings."""
    from fieldtool.run.outdir import strict_json

    extra: list[str] = []
    summary = strict_json(result.summary(), extra)
    if extra:
        summary["warnings"] = list(summary.get("warnings") or []) + extra
    atomic_write_bytes(out / "result.json", json.dumps(summary, indent=2, default=_json_default,
                                                       allow_nan=False).encode())


def _write_outputs(result: RunResult, inputs: Inputs, out: Path) -> None:
    d, p = result.discharge, result.piv
    files = result.files
    lines = ["subsection,station_from_m,station_to_m,area_m2,mean_depth_m,surface_velocity_ms,velocity_filled,discharge_m3s,stiv_velocity_ms"]
    stiv_v = stiv_stage.stiv_column(result.stiv, len(d.area_m2))
    for i in range(len(d.area_m2)):
        lines.append(f"{i + 1},{d.station_from[i]:.4f},{d.station_to[i]:.4f},{d.area_m2[i]:.5f},{d.mean_depth_m[i]:.4f},"
                     f"{d.surface_velocity_ms[i]:.5f},{int(d.velocity_filled[i])},{d.sub_discharge_m3s[i]:.5f},{stiv_v[i]}")
    atomic_write_bytes(out / "subsections.csv", ("\n".join(lines) + "\n").encode())
    files["subsections"] = "subsections.csv"

    XY = result.mapping.image_to_world(np.c_[p.x.ravel(), p.y.ravel()]).reshape(p.x.shape + (2,))
    arrays = dict(x_px=p.x, y_px=p.y, u_px_s=p.u, v_px_s=p.v, X_m=XY[..., 0], Y_m=XY[..., 1], U_ms=result.world_u,
                  V_ms=result.world_v, valid=p.valid, valid_fraction=p.valid_fraction, H=result.mapping.H,
                  water_level_m=np.float64(d.water_level_m), discharge_m3s=np.float64(d.discharge_m3s))
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(out / "mean_field.npz", buf.getvalue())
    buf = io.BytesIO()
    np.save(buf, np.stack([p.x, p.y, XY[..., 0], XY[..., 1], result.world_u, result.world_v], axis=-1))
    atomic_write_bytes(out / "mean_field.npy", buf.getvalue())
    files["mean_field"] = "mean_field.npz"
    files["mean_field_npy"] = "mean_field.npy"
    files["result"] = "result.json"


def _write_figures(result: RunResult, inputs: Inputs, out: Path) -> None:
    """vectors.png, rectified.png, section.png (drawn by the figure process during the Monte Carlo, else here)
    and water_level.png (drawn there during the PIV, else here). matplotlib is imported only to draw here."""
    files = result.files
    pre = result.prerendered
    for key, name, draw in (
            ("vectors_png", "vectors.png", lambda p, f: p.plot_vectors(f, inputs.first_color, result, inputs)),
            ("rectified_png", "rectified.png", lambda p, f: p.plot_rectified(f, inputs.first_color, result, inputs)),
            ("section_png", "section.png", lambda p, f: p.plot_section(f, inputs.cross_section, result))):
        png = pre.file(name) if pre is not None else None  # drawn by the figure process
        if png:
            atomic_write_bytes(out / name, png)
            files[key] = name
        else:
            from fieldtool.plots import discharge as plots

            files[key] = draw(plots, out / name).name
    try:
        png = pre.file("water_level.png") if pre is not None else None
        if png:
            atomic_write_bytes(out / "water_level.png", png)
            files["water_level_png"] = "water_level.png"
        else:
            from fieldtool.plots.water_level import plot_level

            files["water_level_png"] = plot_level(out / "water_level.png", inputs.cross_section, result.level).name
    except FieldToolError as e:
        result.warnings.append(f"water-level plot not written: {e}")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
