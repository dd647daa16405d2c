"""Pinhole camera for synthetic scenes: pose from a position and a target, OpenCV conventions.

World: right-handed X, Y, Z (metres) with Z up. Image: x right, y down, origin at the centre of
the top-left pixel. ``R``, ``t`` map world to camera coordinates (``x_cam = R X + t``, as
``cv2.projectPoints``); the camera looks along its +z axis, image x along camera +x, y along +y.
Distortion follows OpenCV's model ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np


@dataclass(frozen=True)
class Camera:
    """A camera looking from ``position_m`` at ``target_m`` (world metres).

    Parameters
    ----------
    position_m, target_m : (X, Y, Z) in metres.
    hfov_deg : horizontal field of view of the pinhole K (degrees), before distortion.
    width_px, height_px : image size (pixels).
    up_hint : world direction that appears "up" in the image (default +Z); give another axis for a
        camera looking straight down.
    dist : OpenCV distortion ``(k1, k2, p1, p2, k3)``; all zeros = ideal pinhole.
    """

    position_m: tuple[float, float, float]
    target_m: tuple[float, float, float]
    hfov_deg: float = 70.0
    width_px: int = 1280
    height_px: int = 720
    up_hint: tuple[float, float, float] = (0.0, 0.0, 1.0)
    dist: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    @cached_property
    def K(self) -> np.ndarray:
        """3x3 camera matrix (pixels); principal point at the image centre."""
        f = (self.width_px / 2.0) / np.tan(np.radians(self.hfov_deg) / 2.0)
        return np.array([[f, 0.0, (self.width_px - 1) / 2.0], [0.0, f, (self.height_px - 1) / 2.0], [0.0, 0.0, 1.0]])

    @cached_property
    def R(self) -> np.ndarray:
        """3x3 world-to-camera rotation; rows are the camera's right, down and forward axes."""
        c = np.asarray(self.position_m, float)
        fwd = np.asarray(self.target_m, float) - c
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(self.up_hint, float))
        n = np.linalg.norm(right)
        if n < 1e-9:
            raise ValueError("camera: up_hint is parallel to the viewing direction; give another up_hint")
        right /= n
        down = np.cross(fwd, right)
        return np.vstack([right, down, fwd])

    @cached_property
    def t(self) -> np.ndarray:
        """Translation (m): ``x_cam = R X + t``."""
        return -self.R @ np.asarray(self.position_m, float)

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues vector of ``R``."""
        return cv2.Rodrigues(self.R)[0].ravel()

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, float)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist_array != 0.0))

    def project(self, world: np.ndarray, distort: bool = True) -> np.ndarray:
        """Pixel coordinates (N, 2) of world points (N, 3) in metres, through the lens model."""
        pts = np.asarray(world, float).reshape(-1, 1, 3)
        d = self.dist_array if distort else np.zeros(5)
        img, _ = cv2.projectPoints(pts, self.rvec, self.t, self.K, d)
        return img.reshape(-1, 2)

    def plane_homography(self, level_m: float) -> np.ndarray:
        """3x3 homography from world (X, Y) on the plane Z = ``level_m`` to undistorted pixels."""
        R = self.R
        M = np.column_stack([R[:, 0], R[:, 1], R[:, 2] * level_m + self.t])
        H = self.K @ M
        return H / H[2, 2]

    def undistorted_of_distorted(self, pts: np.ndarray) -> np.ndarray:
        """Ideal (pinhole) pixel coordinates of observed (distorted) pixels (N, 2), refined with
        Newton steps on ``project`` so the round trip is exact to ~1e-6 px."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return pts.copy()
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        und = cv2.undistortPoints(
            pts.reshape(-1, 1, 2), self.K, self.dist_array, R=np.eye(3), P=np.eye(3), criteria=crit
        ).reshape(-1, 2)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        # Newton refinement in normalised coordinates on the forward model
        xd = (pts[:, 0] - cx) / fx
        yd = (pts[:, 1] - cy) / fy
        x, y = und[:, 0].copy(), und[:, 1].copy()
        for _ in range(5):
            fxv, fyv, j = _distort_jac(x, y, self.dist_array)
            rx, ry = fxv - xd, fyv - yd
            det = j[0] * j[3] - j[1] * j[2]
            x -= (j[3] * rx - j[1] * ry) / det
            y -= (-j[2] * rx + j[0] * ry) / det
        return np.column_stack([x * fx + cx, y * fy + cy])


def _distort_jac(x: np.ndarray, y: np.ndarray, d: np.ndarray):
    """OpenCV distortion of normalised coords and its Jacobian (dxd/dx, dxd/dy, dyd/dx, dyd/dy)."""
    k1, k2, p1, p2, k3 = d[:5]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drad = k1 + 2 * k2 * r2 + 3 * k3 * r2**2  # d rad / d r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    dxdx = rad + x * drad * 2 * x + 2 * p1 * y + p2 * 6 * x
    dxdy = x * drad * 2 * y + 2 * p1 * x + p2 * 2 * y
    dydx = y * drad * 2 * x + p1 * 2 * x + 2 * p2 * y
    dydy = rad + y * drad * 2 * y + p1 * 6 * y + 2 * p2 * x
    return xd, yd, (dxdx, dxdy, dydx, dydy)


def distortion_maps(cam: Camera, margin_px: int = 4) -> tuple[np.ndarray, np.ndarray, tuple[int, int], tuple[int, int]]:
    """Remap tables that sample an undistorted render to produce the distorted image.

    Returns ``map_x, map_y`` (float32, image size) in the coordinates of an enlarged undistorted
    canvas, the canvas ``offset`` (ox, oy) to add to ideal pixel coordinates, and the canvas size
    (width, height).
    """
    w, h = cam.width_px, cam.height_px
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    und = cam.undistorted_of_distorted(np.column_stack([xs.ravel(), ys.ravel()]))
    lo = np.floor(und.min(axis=0)) - margin_px
    hi = np.ceil(und.max(axis=0)) + margin_px
    ox, oy = int(-lo[0]), int(-lo[1])
    cw, ch = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    map_x = (und[:, 0] + ox).reshape(h, w).astype(np.float32)
    map_y = (und[:, 1] + oy).reshape(h, w).astype(np.float32)
    return map_x, map_y, (ox, oy), (cw, ch)


def render_canvas(
    cam: Camera,
) -> tuple[np.ndarray | None, np.ndarray | None, tuple[int, int], tuple[int, int], np.ndarray]:
    """Where to render an ideal (pinhole) view before the lens is applied.

    Returns ``(map_x, map_y, offset, canvas_size, T)``: remap tables from the distorted frame into the
    (enlarged) ideal canvas, or None without distortion; the canvas offset and size (px); and ``T``,
    the 3x3 shift from ideal image pixels to canvas pixels.
    """
    map_x: np.ndarray | None
    map_y: np.ndarray | None
    if cam.has_distortion:
        map_x, map_y, offset, canvas = distortion_maps(cam)
    else:
        map_x = map_y = None
        offset, canvas = (0, 0), (cam.width_px, cam.height_px)
    T = np.array([[1.0, 0, offset[0]], [0, 1.0, offset[1]], [0, 0, 1.0]])
    return map_x, map_y, offset, canvas, T
