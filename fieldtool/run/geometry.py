"""Stages 2 and 3, level and mapping, then the section: the water level (by the project's method), the
image -> water-plane mapping (orthorectification), the section of interest checked against the
cross-section's water edges, and the ROI and masks in working-image pixels. Units: m, px."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldtool.errors import GeometryError, ParameterError
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho, pose, water_level, waterline
from fieldtool.processing.calibration import LensModel
from fieldtool.processing.masks import rasterize
from fieldtool.project.model import Project
from fieldtool.project.sections import SectionSpec
from fieldtool.run.inputs import Inputs


def detect_waterline(project: Project, inputs: Inputs, mapping: ortho.OrthoMapping | None = None) -> dict:
    """Water edges found along the search line in the clip's first frames (processing.waterline): the
    project's ``water_level.search_line_px``, else the section's points lengthened by 40 % each way; with a
    ``mapping``, also along 2 lines each side of it, ``water_level.search_spacing_m`` apart on the water."""
    wl = project.water_level
    if wl.search_line_px:
        line = inputs.to_working(wl.search_line_px)
        if line.shape != (2, 2):
            raise ParameterError("water_level.search_line_px: give two [x, y] pixel points, one on each bank")
    else:
        sec = np.asarray(project.section.points_px, float)
        if sec.shape != (2, 2):
            raise ParameterError(
                "water_level.search_line_px: draw a line from bank to bank across the river "
                "(or pick the section's water edges, which it extends)"
            )
        p0, p1 = inputs.to_working(sec)
        line = waterline.extend_line(p0, p1, 0.4, inputs.shape)
    lines = (
        waterline.parallel_lines(line, mapping, wl.search_spacing_m, 2, inputs.shape)
        if mapping is not None
        else [(0.0, line)]
    )
    frames = (inputs.lens.undistort(f.image) if inputs.lens is not None else f.image for f in inputs.source)
    return waterline.detect_water_edges(frames, lines)


def compute_level(project: Project, inputs: Inputs, mapping: ortho.OrthoMapping | None):
    """Water level by the project's method (see processing.water_level)."""
    detected = detect_waterline(project, inputs, mapping) if project.water_level.method == "waterline" else None
    sec = project.section
    station_of = None  # with a surveyed station of the section's first point, each edge gives a level too
    if detected is not None and sec.station_offset_m is not None and np.shape(sec.points_px) == (2, 2):
        station_of = waterline.station_function(inputs.to_working(sec.points_px), mapping, sec.station_offset_m)
    fov = inputs.lens.fov_deg() if inputs.lens is not None else None
    return water_level.compute_level(
        project.water_level,
        inputs.cross_section,
        root=project.root,
        mapping=mapping,
        fov_deg=fov,
        points_transform=inputs.to_working if inputs.lens is not None else None,
        image_undistort=inputs.lens.undistort_points_in if inputs.lens is not None else None,
        detected=detected,
        station_of=station_of,
    )


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
        return ortho.from_distances(
            inputs.to_working(raw),
            o.distances_m,
            max_residual_m=o.max_residual_m,
            accept_residual=o.accept_residual,
            frame_shape=shape,
        )
    if o.method == "two_points":
        raw = np.asarray(o.gcp_px, float)
        if raw.shape != (2, 2):
            raise ParameterError("ortho.gcp_px: give exactly two [x, y] pixel points P1, P2 for method = two_points")
        ortho.check_in_frame(raw, shape, "ortho.gcp_px")
        return ortho.from_two_points(
            inputs.to_working(raw), o.distances_m[0] if len(o.distances_m) == 1 else None, o.gcp_world_m or None
        )
    if o.method == "world":
        raw = np.asarray(o.gcp_px, float)
        ortho.check_in_frame(raw.reshape(-1, 2), shape, "ortho.gcp_px")
        m = ortho.from_world_points(inputs.to_working(raw), o.gcp_world_m)
        ortho.check_gcp_residuals(m, inputs.to_working(raw), o.max_residual_m, o.accept_residual)
        return m
    if o.method == "pose":
        if level_m is None:
            raise ParameterError("ortho.method = pose needs the water level first")
        raw = np.asarray(o.gcp_px, float)
        world = np.asarray(o.gcp_world_m, float)
        lens_fit = None
        if inputs.lens is None:
            if not o.fit_lens:
                raise ParameterError(
                    "ortho.method = pose needs the camera intrinsics: set calibration.path, or set "
                    "ortho.fit_lens = true to fit focal length and k1 from 8+ GCPs"
                )
            h, w = shape
            K, dist, p, lens_fit = pose.fit_lens(raw, world, (w, h))
            inputs.lens = LensModel(K, dist, (w, h), rms_px=lens_fit["rms_px"])  # frames are undistorted with it
        else:
            p = pose.solve_pose(raw, world, inputs.lens.camera_matrix, inputs.lens.dist_coeffs)
        H = pose.plane_homography(p, level_m)
        # residual in metres: each GCP's ray met on the horizontal plane at its own elevation
        und = inputs.to_working(raw)
        miss = [
            np.hypot(*(ortho._apply(pose.plane_homography(p, z), und[i : i + 1])[0] - world[i, :2]))
            for i, z in enumerate(world[:, 2])
        ]
        details = {
            "reprojection_rms_px": p.rms_px,
            "gcp_residual_m": [float(m) for m in miss],
            "gcp_reprojection_px": [float(r) for r in p.reprojection_px],
        }
        if lens_fit is not None:
            details["lens_from_gcps"] = lens_fit
        m = ortho.from_homography(H, "pose", float(np.sqrt(np.mean(np.square(miss)))), world[:, :2], details)
        ortho.check_gcp_residuals(m, und, o.max_residual_m, o.accept_residual)
        return m
    if o.method == "none":
        if level_m is None:
            raise ParameterError(
                "ortho.method = none takes the image scale from the wetted width: the water level is needed first"
            )
        pts = inputs.to_working(project.section.points_px)
        if pts.shape != (2, 2):
            raise ParameterError("section.points_px: give the two water edges; without GCPs they set the image scale")
        # the picked points are the OUTER water edges, so the scale is their distance on the cross-section,
        # not the wetted width (which leaves out islands: -8.3 % with a 1 m island in 12 m)
        length_px = float(np.hypot(*(pts[1] - pts[0])))
        left, right = inputs.cross_section.water_edges(level_m)
        return ortho.from_scale((right - left) / length_px)
    raise ParameterError(f"ortho.method: {o.method!r} is not one of distances, world, pose, two_points, none")


def build_section(
    project: Project, inputs: Inputs, level_m: float, mapping: ortho.OrthoMapping, points_px=None
) -> dq.SectionGeometry:
    """The section of interest (raw-frame ``points_px``, default the project's), checked against the water
    edges of the cross-section at ``level_m`` (see processing.discharge.check_section)."""
    sec = project.section
    pts = sec.points_px if points_px is None else points_px
    if np.asarray(pts).shape == (2, 2):  # raw-frame pixels, checked before undistortion
        ortho.check_in_frame(np.asarray(pts, float), inputs.shape, "section.points_px")
    geom = dq.section_geometry(
        inputs.to_working(pts) if len(pts) else pts,
        mapping,
        inputs.cross_section,
        level_m,
        sec.n_sub,
        sec.station_offset_m,
        footprint_px=dq.window_reach_px(project.piv.window_px),
    )
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
        polys = [inputs.to_working(p).tolist() if len(p) >= 3 else p for p in project.roi.masks_px]
        mask = rasterize((h, w), polys)
    return roi, mask


@dataclass
class Sections:
    """The section stage's output: the main section, the user's ROI and mask (working-image px) and the
    segments PIV must cover (the main section's, then each extra section's, (2, 2) working-image px)."""

    geom: dq.SectionGeometry
    roi: tuple[int, int, int, int] | None
    mask: np.ndarray | None
    segments: list
    extra: list[SectionSpec]


def place_sections(
    project: Project, inputs: Inputs, level_m: float, mapping: ortho.OrthoMapping, extra: list[SectionSpec]
) -> Sections:
    """The main section (checked, see :func:`build_section`), the ROI and mask, and the segments of all
    sections."""
    geom = build_section(project, inputs, level_m, mapping)
    roi, mask = roi_and_mask(project, inputs)
    segments = [geom.p_img] + [inputs.to_working(s.points_px) for s in extra if len(s.points_px)]
    return Sections(geom, roi, mask, segments, extra)
