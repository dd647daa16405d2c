"""Lens calibration: a rendered checkerboard video of a known camera, bad inputs, file round trip, real video."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from fieldtool.errors import Cancelled, InputFileError, ParameterError
from fieldtool.processing.calibration import LensModel, calibrate_video, load_calibration, save_calibration

DATA = Path(__file__).parents[2] / ".." / "shared" / "data"
REAL = DATA / "real"
needs_data = pytest.mark.skipif(
    not DATA.is_dir(), reason=f"real data folder {DATA} is absent (only CI and the dev machine have it)"
)

W, H = 640, 480
K_TRUE = np.array([[500.0, 0, 322.0], [0, 500.0, 238.0], [0, 0, 1]])
D_TRUE = np.array([-0.25, 0.05, 0.0, 0.0, 0.0])
COLS, ROWS = 9, 6  # inner corners
S = 40  # texture pixels per square


def _board_texture() -> np.ndarray:
    """Board in 'square' units: inner corner (i, j) at X = i, Y = j; one white square of margin."""
    u = np.arange((COLS + 3) * S)
    v = np.arange((ROWS + 3) * S)
    X = (u + 0.5) / S - 2
    Y = (v + 0.5) / S - 2
    xi, yi = np.floor(X), np.floor(Y)
    inside_x = (X >= -1) & (X < COLS)
    inside_y = (Y >= -1) & (Y < ROWS)
    black = ((xi[None, :] + yi[:, None]) % 2 == 0) & inside_x[None, :] & inside_y[:, None]
    tex = np.where(black, 30.0, 225.0).astype(np.float32)
    return cv2.GaussianBlur(tex, (0, 0), 0.8)


_TEX = _board_texture()
_GRID = np.stack(np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64)), -1).reshape(-1, 2)


def _rays(K, dist) -> np.ndarray:
    """Normalised undistorted ray (x, y, 1) of every pixel of the distorted image."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)
    n = cv2.undistortPoints(_GRID.reshape(-1, 1, 2), K, dist, criteria=crit).reshape(-1, 2)
    return np.c_[n, np.ones(len(n))]


def _render(rays: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Gray image of the board at pose (R, t) (board units -> camera), seen through ``rays``."""
    M = np.column_stack([R[:, 0], R[:, 1], t])
    b = rays @ np.linalg.inv(M).T
    X, Y = b[:, 0] / b[:, 2], b[:, 1] / b[:, 2]
    mx = ((X + 2) * S - 0.5).reshape(H, W).astype(np.float32)
    my = ((Y + 2) * S - 0.5).reshape(H, W).astype(np.float32)
    img = cv2.remap(_TEX, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
    return np.clip(img, 0, 255).astype(np.uint8)


def _poses(n: int, seed: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses spread over the image, tilted up to 35°, fully in view."""
    rng = np.random.default_rng(seed)
    out = []
    outline = np.array([[-1.5, -1.5, 0], [COLS + 0.5, -1.5, 0], [COLS + 0.5, ROWS + 0.5, 0], [-1.5, ROWS + 0.5, 0]])
    while len(out) < n:
        rvec = np.radians([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-20, 20)])
        R = cv2.Rodrigues(rvec)[0]
        z = rng.uniform(16, 24)
        target = np.array([rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * H, 1.0])
        centre = np.linalg.inv(K_TRUE) @ target * z
        t = centre - R @ np.array([(COLS - 1) / 2, (ROWS - 1) / 2, 0])
        px, _ = cv2.projectPoints(outline, rvec, t, K_TRUE, D_TRUE)
        px = px.reshape(-1, 2)
        if px[:, 0].min() > 5 and px[:, 0].max() < W - 5 and px[:, 1].min() > 5 and px[:, 1].max() < H - 5:
            out.append((R, t))
    return out


def _blank(rng) -> np.ndarray:
    return cv2.GaussianBlur((rng.random((H, W)) * 255).astype(np.uint8), (0, 0), 3)


def _write(path: Path, frames: list[np.ndarray]) -> Path:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10, (W, H), False)
    assert vw.isOpened()
    for f in frames:
        vw.write(f)
    vw.release()
    return path


@pytest.fixture(scope="module")
def board_video(tmp_path_factory) -> Path:
    rng = np.random.default_rng(0)
    rays = _rays(K_TRUE, D_TRUE)
    frames = [_blank(rng) for _ in range(4)]  # no board in the first frames: the first part must look further
    frames += [_render(rays, R, t) for R, t in _poses(20)]
    return _write(tmp_path_factory.mktemp("calib") / "board.mkv", frames)


def test_recovers_known_camera(board_video):
    progress = []
    m = calibrate_video(
        board_video, (COLS, ROWS), square_mm=30.0, n_frames=12, progress=lambda d, t: progress.append((d, t))
    )
    assert m.image_size == (W, H)
    assert m.fx == pytest.approx(K_TRUE[0, 0], rel=0.01)
    assert m.fy == pytest.approx(K_TRUE[1, 1], rel=0.01)
    assert m.dist_coeffs[0] == pytest.approx(D_TRUE[0], abs=0.02)
    assert m.rms_px < 0.3
    assert len(m.frames_used) >= 10 and min(m.frames_used) >= 4  # blank frames 0-3 were skipped
    assert progress[-1] == (24, 24)
    # the recovered model straightens the lens: points match the true undistortion
    pts = np.array([[80.0, 70.0], [560.0, 410.0], [320.0, 240.0], [100.0, 400.0]])  # where boards were seen
    truth = LensModel(K_TRUE, D_TRUE, (W, H)).undistort_points(pts)
    assert np.abs(m.undistort_points(pts) - truth).max() < 0.5


def test_cancel(board_video):
    with pytest.raises(Cancelled):
        calibrate_video(board_video, (COLS, ROWS), n_frames=12, cancel=lambda: True)


def test_no_board_is_a_clear_error(tmp_path):
    rng = np.random.default_rng(3)
    video = _write(tmp_path / "blank.mkv", [_blank(rng) for _ in range(12)])
    with pytest.raises(InputFileError, match="no checkerboard with 9 x 6 inner corners"):
        calibrate_video(video, (9, 6), n_frames=6)


def test_too_few_boards_is_a_clear_error(tmp_path):
    rng = np.random.default_rng(4)
    rays = _rays(K_TRUE, D_TRUE)
    frames = [_blank(rng) for _ in range(18)]
    for k, (R, t) in zip((2, 9), _poses(2, seed=5), strict=True):
        frames[k] = _render(rays, R, t)
    video = _write(tmp_path / "few.mkv", frames)
    with pytest.raises(InputFileError, match="found in only 2 of the 6 parts"):
        calibrate_video(video, (9, 6), n_frames=6)


def test_bad_arguments(tmp_path, board_video):
    with pytest.raises(InputFileError, match="not found"):
        calibrate_video(tmp_path / "missing.mp4")
    not_video = tmp_path / "x.mp4"
    not_video.write_text("hello")
    with pytest.raises(InputFileError):
        calibrate_video(not_video)
    with pytest.raises(ParameterError, match="calibration.corners"):
        calibrate_video(board_video, (6, 6))
    with pytest.raises(ParameterError, match="calibration.square_mm"):
        calibrate_video(board_video, square_mm=0)
    with pytest.raises(ParameterError, match="calibration.n_frames"):
        calibrate_video(board_video, n_frames=2)


def test_fov_thesis_formulas():
    m = LensModel(np.array([[640.0, 0, 640], [0, 360.0, 360], [0, 0, 1]]), np.zeros(5), (1280, 720))
    fx, fy, fd = m.fov_deg()
    assert fx == pytest.approx(90.0)
    assert fy == pytest.approx(90.0)
    assert fd == pytest.approx(math.degrees(2 * math.atan(math.hypot(1280, 720) / (2 * 500.0))))


def test_undistort_points_inverts_the_lens():
    m = LensModel(K_TRUE, D_TRUE, (W, H))
    rng = np.random.default_rng(0)
    rays = np.c_[rng.uniform(-0.55, 0.55, 50), rng.uniform(-0.4, 0.4, 50), np.ones(50)]
    raw, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K_TRUE, D_TRUE)
    ideal = rays[:, :2] @ K_TRUE[:2, :2].T + K_TRUE[:2, 2]
    assert np.abs(m.undistort_points(raw.reshape(-1, 2)) - ideal).max() < 1e-4
    assert np.abs(m.distort_points(ideal) - raw.reshape(-1, 2)).max() < 1e-4
    assert m.undistort_points(np.empty((0, 2))).shape == (0, 2)


def test_undistort_image_straightens_the_board():
    rays = _rays(K_TRUE, D_TRUE)
    R, t = _poses(1, seed=11)[0]
    m = LensModel(K_TRUE, D_TRUE, (W, H))
    img = m.undistort(_render(rays, R, t))
    assert img.shape == (H, W) and img.dtype == np.uint8
    ok, found = cv2.findChessboardCorners(img, (COLS, ROWS))
    assert ok
    found = cv2.cornerSubPix(img, found, (5, 5), (-1, -1), (3, 40, 0.001)).reshape(-1, 2)
    board = np.c_[np.mgrid[0:COLS, 0:ROWS].T.reshape(-1, 2), np.zeros(COLS * ROWS)]
    ideal = cv2.projectPoints(board, cv2.Rodrigues(R)[0], t, K_TRUE, None)[0].reshape(-1, 2)
    assert np.abs(found - ideal).max() < 0.3
    with pytest.raises(ParameterError, match="calibrate with a video at the same resolution"):
        m.undistort(np.zeros((100, 100), np.uint8))


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_save_load_round_trip(tmp_path, suffix):
    m = LensModel(K_TRUE, D_TRUE, (W, H), 0.21, [3, 9])
    path = tmp_path / f"lens{suffix}"
    save_calibration(m, path)
    back = load_calibration(path)
    np.testing.assert_array_equal(back.camera_matrix, K_TRUE)
    np.testing.assert_array_equal(back.dist_coeffs, D_TRUE)
    assert back.image_size == (W, H) and back.rms_px == 0.21 and back.frames_used == [3, 9]
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left behind


def test_load_errors(tmp_path):
    with pytest.raises(InputFileError, match="calibration file not found"):
        load_calibration(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("camera_matrix = [[1, 0")
    with pytest.raises(InputFileError, match="not a valid calibration file"):
        load_calibration(bad)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"lens": {"camera_matrix": K_TRUE.tolist(), "image_size": [W, H]}}))
    with pytest.raises(InputFileError, match="lacks 'dist_coeffs'"):
        load_calibration(partial)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps({"camera_matrix": [[1, 2], [3, 4]], "dist_coeffs": [0, 0, 0, 0], "image_size": [W, H]}))
    with pytest.raises(InputFileError, match="3x3"):
        load_calibration(wrong)


@needs_data
def test_loads_pyorc_camera_config():
    m = load_calibration(REAL / "geul_dk_cam_config.json")
    assert m.image_size == (1920, 1080)
    assert m.fx == pytest.approx(1551.26, abs=0.01)
    assert m.dist_coeffs[:2] == pytest.approx([-0.3562, 0.0482], abs=1e-4)


@needs_data
@pytest.mark.slow
def test_real_checkerboard_video():
    """The container claims 401 frames, about 353 decode; 9 x 6 inner corners; square size unknown."""
    m = calibrate_video(REAL / "camera_calib_720p.mkv", (9, 6), square_mm=25.0, n_frames=20)
    assert m.image_size == (1280, 720)
    assert m.rms_px < 1.0
    assert len(m.frames_used) >= 15 and max(m.frames_used) < 360
    assert m.fx / m.fy == pytest.approx(1.0, abs=0.02)  # square pixels
    cx, cy = m.camera_matrix[0, 2], m.camera_matrix[1, 2]
    assert abs(cx - 640) < 64 and abs(cy - 360) < 64  # principal point near the centre
