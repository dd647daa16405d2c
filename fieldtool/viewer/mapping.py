"""Pure geometry between the viewer's 3-D scene, image pixels and plot axes.

The viewer shows an image as a flat rectangle in a 3-D scene (viser). A click arrives as a ray
(origin and direction, scene units); :func:`ray_to_pixel` intersects it with the image plane and
returns pixel coordinates in the OpenCV convention used everywhere in fieldtool: x right, y down,
origin at the centre of the top-left pixel, so the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5].

Viser draws an image in its local frame with x to the right, y down (row index growing with +y)
and the image centred on the origin of the plane z = 0; the camera that shows it upright sits on
the -z side looking towards +z with its up vector along -y (the OpenCV camera convention).

Nothing here imports viser: these functions are unit-tested on their own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ImagePlane:
    """Where an image of ``width_px`` x ``height_px`` pixels is drawn in the scene.

    ``render_width`` x ``render_height`` (scene units) is the size of the drawn rectangle,
    ``position`` (3,) its centre and ``rotation`` (3, 3) the rotation from the image's local frame
    (x right, y down, z away from the viewer) to the scene frame.
    """

    width_px: int
    height_px: int
    render_width: float
    render_height: float
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def units_per_px(self) -> tuple[float, float]:
        """Scene units per pixel along x and y."""
        return self.render_width / self.width_px, self.render_height / self.height_px


def fit_plane(width_px: int, height_px: int, size: float = 10.0) -> ImagePlane:
    """An upright image plane at the origin whose longer side is ``size`` scene units."""
    if width_px <= 0 or height_px <= 0:
        raise ValueError(f"image size must be positive, got {width_px} x {height_px} px")
    s = size / max(width_px, height_px)
    return ImagePlane(int(width_px), int(height_px), width_px * s, height_px * s)


def ray_to_pixel(origin, direction, plane: ImagePlane) -> np.ndarray | None:
    """Pixel (x, y) where a ray meets the image plane, or ``None`` if it never does.

    Parameters
    ----------
    origin, direction : array_like, shape (3,)
        Ray in scene coordinates (``direction`` need not be unit length).
    plane : ImagePlane
        Where the image is drawn.

    Returns
    -------
    numpy.ndarray of shape (2,) or None
        Pixel coordinates (px, OpenCV convention); may lie outside the image (see
        :func:`inside`). ``None`` when the ray is parallel to the plane or points away from it.
    """
    R = np.asarray(plane.rotation, float)
    o = R.T @ (np.asarray(origin, float) - np.asarray(plane.position, float))
    d = R.T @ np.asarray(direction, float)
    if abs(d[2]) < 1e-12:
        return None
    t = -o[2] / d[2]
    if t < 0:
        return None
    lx, ly = o[0] + t * d[0], o[1] + t * d[1]
    x = (lx / plane.render_width + 0.5) * plane.width_px - 0.5
    y = (ly / plane.render_height + 0.5) * plane.height_px - 0.5
    return np.array([x, y])


def pixel_to_scene(pts, plane: ImagePlane, lift: float = 0.0) -> np.ndarray:
    """Scene coordinates (N, 3) of pixel points (N, 2), raised ``lift`` units towards the viewer.

    The inverse of :func:`ray_to_pixel` on the plane; ``lift`` keeps overlays drawn in front of
    the image.
    """
    p = np.asarray(pts, float).reshape(-1, 2)
    lx = ((p[:, 0] + 0.5) / plane.width_px - 0.5) * plane.render_width
    ly = ((p[:, 1] + 0.5) / plane.height_px - 0.5) * plane.render_height
    local = np.c_[lx, ly, np.full(len(p), -lift)]
    return local @ np.asarray(plane.rotation, float).T + np.asarray(plane.position, float)


def inside(plane: ImagePlane, xy) -> bool:
    """True when pixel ``xy`` lies on the image (edges included)."""
    x, y = float(xy[0]), float(xy[1])
    return -0.5 <= x <= plane.width_px - 0.5 and -0.5 <= y <= plane.height_px - 0.5


def camera_pose(plane: ImagePlane, fov_y_rad: float, aspect: float, margin: float = 1.05):
    """Camera (position, look_at, up) that shows the whole image upright.

    Parameters
    ----------
    plane : ImagePlane
    fov_y_rad : float
        Vertical field of view (rad).
    aspect : float
        Viewport width / height.
    margin : float
        1 = image touches the viewport edges; larger leaves a border.
    """
    t = np.tan(fov_y_rad / 2.0)
    d = margin * max(plane.render_height / 2.0 / t, plane.render_width / 2.0 / (t * aspect))
    R = np.asarray(plane.rotation, float)
    c = np.asarray(plane.position, float)
    return c + R @ np.array([0.0, 0.0, -d]), c, R @ np.array([0.0, -1.0, 0.0])


@dataclass(frozen=True)
class PlotAxes:
    """Linear axes of a plot image: data (x, y) <-> pixel (column, row).

    ``left_px``/``right_px`` are the pixel columns of ``x_min``/``x_max``; ``top_px``/``bottom_px``
    the pixel rows of ``y_max``/``y_min`` (y grows upwards in data, downwards in the image).
    For the DEM-vs-bed plot x is the station (m) and y the elevation (m).
    """

    left_px: float
    right_px: float
    top_px: float
    bottom_px: float
    x_min: float
    x_max: float
    y_min: float
    y_max: float

    def data_to_px(self, pts) -> np.ndarray:
        """(N, 2) data points -> (N, 2) pixels."""
        p = np.asarray(pts, float).reshape(-1, 2)
        col = self.left_px + (p[:, 0] - self.x_min) / (self.x_max - self.x_min) * (self.right_px - self.left_px)
        row = self.bottom_px - (p[:, 1] - self.y_min) / (self.y_max - self.y_min) * (self.bottom_px - self.top_px)
        return np.c_[col, row]

    def px_to_data(self, pts) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) data points."""
        p = np.asarray(pts, float).reshape(-1, 2)
        x = self.x_min + (p[:, 0] - self.left_px) / (self.right_px - self.left_px) * (self.x_max - self.x_min)
        y = self.y_min + (self.bottom_px - p[:, 1]) / (self.bottom_px - self.top_px) * (self.y_max - self.y_min)
        return np.c_[x, y]

    def contains_px(self, xy) -> bool:
        """True when pixel ``xy`` is inside the plotting area."""
        return self.left_px <= xy[0] <= self.right_px and self.top_px <= xy[1] <= self.bottom_px


def zoom_about_cursor(
    position,
    look_at,
    up,
    fov_y_rad: float,
    aspect: float,
    ndc,
    scale: float,
    plane: ImagePlane,
    min_dist: float | None = None,
    max_dist: float | None = None,
):
    """New camera (position, look_at) after a zoom that keeps the point under the cursor fixed.

    The camera (``position``, ``look_at``, ``up``; three.js convention, vertical field of view
    ``fov_y_rad``, viewport ``aspect`` = width / height) is scaled about the point X where the ray
    through the cursor meets the image plane: both the camera and its target move towards X by
    the factor ``scale`` (< 1 zooms in). A point scaled about X with the camera stays on the same
    ray, so X stays under the cursor. ``ndc`` is the cursor in normalised device coordinates (x
    right, y up, -1..1). Returns None when the cursor's ray misses the plane. The distance from
    X is kept within [min_dist, max_dist] (scene units) when given.
    """
    p = np.asarray(position, float)
    t = np.asarray(look_at, float)
    f = t - p
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, float))
    if np.linalg.norm(r) < 1e-12:
        return None
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    h = np.tan(fov_y_rad / 2.0)
    d = f + float(ndc[0]) * h * aspect * r + float(ndc[1]) * h * u
    px = ray_to_pixel(p, d, plane)
    if px is None:
        return None
    x = pixel_to_scene([px], plane)[0]
    dist = float(np.linalg.norm(p - x))
    s = float(scale)
    if min_dist is not None and dist * s < min_dist:
        s = min_dist / dist
    if max_dist is not None and dist * s > max_dist:
        s = max_dist / dist
    return x + (p - x) * s, x + (t - x) * s
