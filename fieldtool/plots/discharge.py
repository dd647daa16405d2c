"""PNG plots of a run: vectors over the first frame, the rectified image with vectors, and the
section profile with subsection velocities. Axes: image pixels (x right, y down) or world metres."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from fieldtool.project.model import atomic_write_bytes

#: margins around a figure's axes (inches: left, right, bottom, top), room for the tick labels, axis labels and
#: title at matplotlib's default sizes. Fixed, not a layout engine: the constrained layout measured every tick
#: label twice before the figure was drawn, about half of a figure's time (a run waits for its velocity figures
#: at its end; 720p, medians of 5 alternating processes: vectors 0.28 -> 0.19 s, rectified 0.21 -> 0.17 s,
#: section 0.22 -> 0.14 s, profile 0.14 -> 0.10 s, gcp 0.25 -> 0.17 s)
MARGINS_IN = (0.85, 0.25, 0.6, 0.45)


def _figure(dpi: float = 100, margins: tuple[float, float, float, float] = MARGINS_IN, **kwargs) -> Figure:
    """A figure on its own Agg canvas: no pyplot state, safe in worker threads and processes. Its axes fill it
    but for ``margins`` (inches: left, right, bottom, top; see :data:`MARGINS_IN`)."""
    fig = Figure(dpi=dpi, **kwargs)
    FigureCanvasAgg(fig)
    w, h = fig.get_size_inches()
    left, right, bottom, top = margins
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h)
    return fig


def _save(fig: Figure, path: Path) -> Path:
    """The figure as a PNG at its own dpi, written atomically. The canvas' print_png lays the figure out and
    draws it in one pass; savefig would draw it twice (once to lay it out)."""
    buf = io.BytesIO()
    canvas = fig.canvas
    assert isinstance(canvas, FigureCanvasAgg)  # _figure gave it one
    canvas.print_png(buf, pil_kwargs={"compress_level": 1})  # zlib 6 costs 4x the time
    atomic_write_bytes(path, buf.getvalue())
    return path


def _working_rgb(first_bgr: np.ndarray, inputs) -> np.ndarray:
    img = first_bgr
    if inputs.lens is not None:
        img = inputs.lens.undistort(img)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _show(ax, rgb: np.ndarray, extent, max_side_px: int = 1000) -> None:
    """imshow of an image already shrunk to about the figure's resolution (the same extent). A uint8 RGB image
    goes in as opaque RGBA: matplotlib stacks an RGB image's alpha as float64 and resamples the whole image in
    float64, an RGBA one in float32; the same pixels in the PNG, 10-15 % less of an image figure's time."""
    scale = max_side_px / max(rgb.shape[:2])
    if scale < 1:
        rgb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    if rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3:
        rgb = cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA)
    ax.imshow(rgb, extent=extent, interpolation="nearest")


def plot_vectors(path: Path, first_bgr: np.ndarray, result, inputs) -> Path:
    """Mean velocity (m/s, colour) as arrows in image pixels over the first working frame."""
    p = result.piv
    rgb = _working_rgb(first_bgr, inputs)
    speed = np.hypot(result.world_u, result.world_v)
    left, _, bottom, top = MARGINS_IN  # the colour bar and its label take their room from the axes' own width
    fig = _figure(figsize=(10, 10 * rgb.shape[0] / rgb.shape[1]), margins=(left, 0.1, bottom, top))
    ax = fig.subplots()
    h, w = rgb.shape[:2]
    _show(ax, rgb, (-0.5, w - 0.5, h - 0.5, -0.5))
    ok = p.valid & np.isfinite(p.u)
    step = max(1, int(np.ceil(max(p.x.shape) / 60)))
    sl = (slice(None, None, step), slice(None, None, step))
    q = ax.quiver(
        p.x[sl][ok[sl]],
        p.y[sl][ok[sl]],
        p.u[sl][ok[sl]],
        p.v[sl][ok[sl]],
        speed[sl][ok[sl]],
        cmap="viridis",
        angles="xy",
        scale_units="xy",
        scale=None,
    )
    fig.colorbar(q, ax=ax, shrink=0.7, label="surface speed (m/s)")
    sp = result.section.p_img
    ax.plot(sp[:, 0], sp[:, 1], "r-", lw=2)
    ax.text(sp[0, 0], sp[0, 1], " P1 (left edge)", color="r")
    ax.set_title(f"Q = {result.discharge.discharge_m3s:.3f} m³/s, mean velocity field (image pixels)", y=1.0)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    return _save(fig, path)


def plot_rectified(path: Path, first_bgr: np.ndarray, result, inputs) -> Path:
    """Orthorectified first frame with the world velocity vectors (m/s) and the section."""
    rgb = _working_rgb(first_bgr, inputs)
    m = result.mapping
    section_w = result.section.p_world
    gw = m.gcp_world if m.gcp_world is not None else section_w
    pts = np.vstack([gw, section_w])
    c = pts.mean(axis=0)
    half = np.ptp(pts, axis=0).max() * 0.8 + 1.0
    bounds = (c[0] - half, c[0] + half, c[1] - half, c[1] + half)
    img, A = m.rectified_image(rgb, bounds_m=bounds, max_side_px=900)
    p = result.piv
    XY = m.image_to_world(np.c_[p.x.ravel(), p.y.ravel()]).reshape(p.x.shape + (2,))
    ok = p.valid & np.isfinite(result.world_u)
    fig = _figure(figsize=(9, 9))
    ax = fig.subplots()
    _show(ax, img, (bounds[0], bounds[1], bounds[2], bounds[3]))
    step = max(1, int(np.ceil(max(p.x.shape) / 50)))
    sl = (slice(None, None, step), slice(None, None, step))
    X, Y = XY[..., 0][sl][ok[sl]], XY[..., 1][sl][ok[sl]]
    U, V = result.world_u[sl][ok[sl]], result.world_v[sl][ok[sl]]
    if len(X) > 1:
        spacing = np.median(np.hypot(np.diff(XY[..., 0][sl], axis=1), np.diff(XY[..., 1][sl], axis=1)))
        vmax = max(float(np.nanmax(np.hypot(U, V))), 1e-6)
        ax.quiver(X, Y, U, V, color="yellow", angles="xy", scale_units="xy", scale=vmax / (0.9 * spacing))
    ax.plot(section_w[:, 0], section_w[:, 1], "r-", lw=2)
    if m.gcp_world is not None:
        ax.plot(m.gcp_world[:, 0], m.gcp_world[:, 1], "c+", ms=12)
        for i, (gx, gy) in enumerate(m.gcp_world):
            ax.text(gx, gy, f" P{i + 1}", color="c")
    ax.set_xlim(bounds[0], bounds[1])
    ax.set_ylim(bounds[2], bounds[3])
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title("Orthorectified first frame, surface velocity (m/s)", y=1.0)
    return _save(fig, path)


def plot_section(path: Path, cs, result) -> Path:
    """Cross-section with the water level, subsections and their surface velocities."""
    d = result.discharge
    level = d.water_level_m
    fig = _figure(figsize=(9, 7))
    ax1, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1.3]})
    mid = 0.5 * (d.station_from + d.station_to)
    colors = np.where(d.velocity_filled, "tab:orange", "tab:blue")
    ax1.bar(mid, d.surface_velocity_ms, width=np.diff(np.r_[d.station_from, d.station_to[-1]]) * 0.9, color=colors)
    ax1.set_ylabel("surface velocity (m/s)")
    ax1.set_title(f"Q = {d.discharge_m3s:.3f} m³/s   alpha = {d.alpha:.2f}   (orange: filled from a neighbour)", y=1.0)
    ax2.plot(cs.station, cs.elevation, "k-", lw=1.5, label="bed")
    ss, depth = cs.wet_polyline(level)
    ax2.fill_between(ss, level - depth, level, where=depth > 0, color="tab:blue", alpha=0.3, label="wetted area")
    ax2.axhline(level, color="tab:blue", lw=1, label=f"water level {level:.3f} m")
    for s in np.r_[d.station_from, d.station_to[-1]]:
        ax2.axvline(s, color="gray", lw=0.5)
    ax2.set_xlabel("station (m, left bank -> right bank)")
    ax2.set_ylabel("elevation (m)")
    ax2.legend(loc="lower right")
    return _save(fig, path)
