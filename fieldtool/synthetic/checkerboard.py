"""Checkerboard calibration video rendered through a known camera (K and distortion).

The board has ``corners = (cols, rows)`` inner corners, i.e. (cols+1) x (rows+1) squares of side
``square_m`` metres, on a white margin of one square. Each frame shows the board at a different
random pose (tilted up to ~35 degrees, 0.7-1.3 m from the camera for a 5 cm square), wholly in view.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from fieldtool.synthetic.camera import Camera, render_canvas

_TEX_PER_SQUARE = 40


def _board_texture(corners: tuple[int, int]) -> np.ndarray:
    cols, rows = corners[0] + 1, corners[1] + 1
    n = _TEX_PER_SQUARE
    tex = np.ones(((rows + 2) * n, (cols + 2) * n), np.float32) * 0.92
    for j in range(rows):
        for i in range(cols):
            if (i + j) % 2 == 0:
                tex[(j + 1) * n : (j + 2) * n, (i + 1) * n : (i + 2) * n] = 0.08
    return tex


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def board_corners(corners: tuple[int, int], square_m: float) -> np.ndarray:
    """Inner corners (cols*rows, 3) in board coordinates (m), row by row, as OpenCV orders them."""
    cols, rows = corners
    g = np.array([[(i + 1) * square_m, (j + 1) * square_m, 0.0] for j in range(rows) for i in range(cols)])
    return g


def render_checkerboard(
    cam: Camera,
    path: Path | str,
    n_frames: int = 40,
    corners: tuple[int, int] = (9, 6),
    square_m: float = 0.05,
    seed: int = 1,
    fps: float = 30.0,
    fourcc: str = "mp4v",
    noise_sigma: float = 2.0,
) -> dict:
    """Write a checkerboard video seen through ``cam`` (its K and distortion) and return the truth:
    ``K``, ``dist``, and per frame the board pose (``rvecs``, ``tvecs``) and the projected inner
    corners (pixels)."""
    path = Path(path)
    w, h = cam.width_px, cam.height_px
    rng = np.random.default_rng(seed)
    map_x, map_y, offset, canvas, T = render_canvas(cam)
    tex = _board_texture(corners)
    ones = np.ones_like(tex)
    sq_tex = square_m / _TEX_PER_SQUARE
    # texel (centre) -> board (m); texel k spans [k - 0.5, k + 0.5], so square edges fall on k = n * j - 0.5
    A = np.array([[sq_tex, 0, 0.5 * sq_tex - square_m], [0, sq_tex, 0.5 * sq_tex - square_m], [0, 0, 1.0]])
    cols, rows = corners
    bw, bh = (cols + 1) * square_m, (rows + 1) * square_m
    outline = np.array(
        [
            [-square_m, -square_m, 0],
            [bw + square_m, -square_m, 0],
            [bw + square_m, bh + square_m, 0],
            [-square_m, bh + square_m, 0],
        ]
    )
    inner = board_corners(corners, square_m)
    background = 0.5 + 0.12 * cv2.resize(
        rng.standard_normal((canvas[1] // 16, canvas[0] // 16)).astype(np.float32),
        canvas,
        interpolation=cv2.INTER_CUBIC,
    )
    scale = square_m / 0.05
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), fps, (w, h), True)
    if not wr.isOpened():
        raise RuntimeError(f"cannot write {fourcc!r} video {path}")
    rvecs: list[np.ndarray] = []
    tvecs: list[np.ndarray] = []
    img_pts: list[np.ndarray] = []
    try:
        while len(rvecs) < n_frames:
            R = _rot(*np.radians(rng.uniform([-35, -35, -25], [35, 35, 25])))
            z = rng.uniform(0.7, 1.3) * scale
            x = rng.uniform(-0.45, 0.45) * z * (w / 2) / cam.K[0, 0]
            y = rng.uniform(-0.45, 0.45) * z * (h / 2) / cam.K[1, 1]
            t = np.array([x, y, z]) - R @ np.array([bw / 2, bh / 2, 0.0])
            rv = cv2.Rodrigues(R)[0].ravel()
            o, _ = cv2.projectPoints(outline.reshape(-1, 1, 3), rv, t, cam.K, cam.dist_array)
            o = o.reshape(-1, 2)
            if (o.min() < 15) or np.any(o[:, 0] > w - 16) or np.any(o[:, 1] > h - 16):
                continue
            H = T @ cam.K @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
            board = cv2.warpPerspective(tex, H, canvas, flags=cv2.INTER_LINEAR)
            alpha = cv2.warpPerspective(ones, H, canvas, flags=cv2.INTER_LINEAR)
            img: np.ndarray = background * (1 - alpha) + board
            if map_x is not None and map_y is not None:
                img = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            img = img * 255.0 + noise_sigma * rng.standard_normal((h, w), dtype=np.float32)
            frame = np.clip(img + 0.5, 0, 255).astype(np.uint8)
            wr.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
            ip, _ = cv2.projectPoints(inner.reshape(-1, 1, 3), rv, t, cam.K, cam.dist_array)
            rvecs.append(rv)
            tvecs.append(t)
            img_pts.append(ip.reshape(-1, 2))
    finally:
        wr.release()
    return {
        "K": cam.K.copy(),
        "dist": cam.dist_array.copy(),
        "corners": tuple(corners),
        "square_m": square_m,
        "rvecs": np.array(rvecs),
        "tvecs": np.array(tvecs),
        "corners_px": np.array(img_pts),
    }
