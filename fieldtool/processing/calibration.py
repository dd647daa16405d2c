"""Lens calibration from a checkerboard video (thesis 7.1, 9.2.3).

The video is split in ``n`` equal parts (by decoded frame); in each part the first frame where
``cv2.findChessboardCorners`` finds the board is kept, and ``cv2.calibrateCamera`` fits the pinhole
camera matrix K and the distortion coefficients (k1, k2, p1, p2, k3) in OpenCV's order.

Undistortion keeps the same camera matrix K: a pixel of the undistorted image is where a perfect
pinhole camera with K would have seen the point. Picked points (GCPs, section, ROI) go through
:meth:`LensModel.undistort_points` so that a pick stays on what the user clicked.

Image axes: x right, y down (px), origin at the top-left pixel centre. K does not depend on the
square size; only the (unused here) board poses do.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import tomli_w

from fieldtool.errors import Cancelled, InputFileError, ParameterError
from fieldtool.project.model import atomic_write_bytes

MIN_VIEWS = 5  # fewer boards than this do not constrain 5 distortion coefficients reliably
_FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
_DETECT_MAX_WIDTH = 1600  # larger frames are searched downscaled, corners refined at full size
_MAX_DECODE_FAILURES = 10  # consecutive frames that fail to decode before the video is taken as ended


@dataclass(eq=False)  # holds arrays: compare fields explicitly
class LensModel:
    """A calibrated pinhole camera with radial and tangential distortion.

    Attributes
    ----------
    camera_matrix : (3, 3) K in pixels: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
    dist_coeffs : (5,) or (4,) distortion coefficients, OpenCV order (k1, k2, p1, p2[, k3]).
    image_size : (width, height) of the calibrated frames (px).
    rms_px : RMS reprojection error of the calibration (px); None when loaded without one.
    frames_used : decoded frame indices of the checkerboard video that were used.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int]
    rms_px: float | None = None
    frames_used: list[int] = field(default_factory=list)
    _maps: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.camera_matrix = np.asarray(self.camera_matrix, dtype=np.float64).reshape(3, 3)
        self.dist_coeffs = np.asarray(self.dist_coeffs, dtype=np.float64).ravel()
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    def fov_deg(self) -> tuple[float, float, float]:
        """Field of view (degrees) along x, y and the diagonal (thesis 7.1.2).

        FOV_x = 2 atan(W / 2 fx), FOV_y = 2 atan(H / 2 fy), FOV_diag = 2 atan(sqrt(W² + H²) / 2 f)
        with f the mean of fx and fy.
        """
        w, h = self.image_size
        f = 0.5 * (self.fx + self.fy)
        fov_x = 2 * math.atan(w / (2 * self.fx))
        fov_y = 2 * math.atan(h / (2 * self.fy))
        fov_d = 2 * math.atan(math.hypot(w, h) / (2 * f))
        return math.degrees(fov_x), math.degrees(fov_y), math.degrees(fov_d)

    def _check_size(self, w: int, h: int, what: str) -> None:
        if (w, h) != self.image_size:
            raise ParameterError(
                f"calibration.path: the lens model is for {self.image_size[0]}x{self.image_size[1]} px frames "
                f"but the {what} is {w}x{h} px; calibrate with a video at the same resolution"
            )

    def undistort(self, img: np.ndarray) -> np.ndarray:
        """The frame as a distortion-free pinhole camera with the same K sees it.

        Same size and dtype as ``img``; the remap tables are computed once and reused, so this is
        cheap enough for every frame.
        """
        h, w = img.shape[:2]
        self._check_size(w, h, "frame")
        if self._maps is None:
            self._maps = cv2.initUndistortRectifyMap(
                self.camera_matrix, self.dist_coeffs, None, self.camera_matrix, (w, h), cv2.CV_16SC2
            )
        return cv2.remap(img, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def undistort_points_in(self, pts: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Undistort (N, 2) pixels of an image of ``shape`` (H, W) taken with this lens at another
        resolution of the same sensor (e.g. a drone photo): scaled to the calibrated size, undistorted,
        scaled back. ParameterError when the aspect ratio differs (another crop of the sensor)."""
        h, w = shape
        W, H = self.image_size
        sx, sy = w / W, h / H
        if abs(sx / sy - 1.0) > 0.01:
            raise ParameterError(
                f"image of {w}x{h} px has not the aspect ratio of the calibrated {W}x{H} frames: "
                "another crop of the sensor; calibrate it, or give water_level.fov_deg without a "
                "calibration"
            )
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2) / [sx, sy]
        return self.undistort_points(p) * [sx, sy]

    def undistort_points(self, pts: np.ndarray) -> np.ndarray:
        """(N, 2) raw (distorted) pixel positions -> (N, 2) undistorted pixel positions, same K."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            return pts.copy()
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
        out = cv2.undistortPoints(
            pts.reshape(-1, 1, 2), self.camera_matrix, self.dist_coeffs, P=self.camera_matrix, criteria=crit
        )
        return out.reshape(-1, 2)

    def distort_points(self, pts: np.ndarray) -> np.ndarray:
        """(N, 2) undistorted pixel positions -> (N, 2) raw pixel positions (inverse of undistort_points)."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            return pts.copy()
        kinv = np.linalg.inv(self.camera_matrix)
        rays = np.c_[pts, np.ones(len(pts))] @ kinv.T
        out, _ = cv2.projectPoints(
            rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.camera_matrix, self.dist_coeffs
        )
        return out.reshape(-1, 2)

    def to_dict(self) -> dict:
        """Plain data for a file: K, distortion, size, RMS and the FOV (degrees, informative)."""
        fx, fy, fd = self.fov_deg()
        d = {
            "camera_matrix": self.camera_matrix.tolist(),
            "dist_coeffs": self.dist_coeffs.tolist(),
            "image_size": list(self.image_size),
            "fov_deg": {"x": fx, "y": fy, "diagonal": fd},
        }
        if self.rms_px is not None:
            d["rms_px"] = float(self.rms_px)
        if self.frames_used:
            d["frames_used"] = [int(i) for i in self.frames_used]
        return d


def _open(path: Path) -> cv2.VideoCapture:
    if not path.is_file():
        raise InputFileError(f"{path}: checkerboard video not found; check calibration.checkerboard_video")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputFileError(f"{path}: cannot be read as a video (unknown format or corrupt file)")
    return cap


def _decoded_frames(cap: cv2.VideoCapture):
    """Yield (index, grab_ok) for every frame; frames that fail to decode are skipped, not counted."""
    idx, failures = 0, 0
    while failures < _MAX_DECODE_FAILURES:
        if not cap.grab():
            failures += 1
            continue
        failures = 0
        yield idx
        idx += 1


def _count_frames(path: Path, cancel: Callable[[], bool] | None) -> int:
    """Frames that really decode (containers often claim more)."""
    cap = _open(path)
    try:
        n = 0
        for n_done in _decoded_frames(cap):
            n = n_done + 1
            if cancel is not None and n % 50 == 0 and cancel():
                raise Cancelled("calibration cancelled")
        return n
    finally:
        cap.release()


def _find_board(gray: np.ndarray, corners: tuple[int, int]) -> np.ndarray | None:
    """Inner-corner positions (N, 1, 2) float32 refined to sub-pixel, or None."""
    h, w = gray.shape
    scale = min(1.0, _DETECT_MAX_WIDTH / w)
    small = (
        gray if scale == 1.0 else cv2.resize(gray, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    )
    ok, pts = cv2.findChessboardCorners(small, corners, flags=_FIND_FLAGS)
    if not ok:
        return None
    pts = (pts / scale).astype(np.float32)
    # refinement window: about a third of the smallest corner spacing, at most 11 px half-size
    grid = pts.reshape(corners[1], corners[0], 2)
    spacing = min(
        np.linalg.norm(np.diff(grid, axis=0), axis=2).min(), np.linalg.norm(np.diff(grid, axis=1), axis=2).min()
    )
    half = int(np.clip(spacing / 3, 2, 11))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.001)
    return cv2.cornerSubPix(gray, pts, (half, half), (-1, -1), crit)


def calibrate_video(
    path: Path | str,
    corners: Sequence[int] = (9, 6),
    square_mm: float | None = 25.0,
    n_frames: int = 20,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> LensModel:
    """Calibrate the camera from a video of a checkerboard (thesis 7.1.2).

    Parameters
    ----------
    path : the checkerboard video (any format ffmpeg reads).
    corners : inner corners of the board (columns, rows), e.g. (9, 6).
    square_mm : side of one square (mm). It scales the board poses only; K and the distortion do
        not depend on it.
    n_frames : the decoded frames are split in this many equal parts; in each the first frame with
        a board found is used (thesis: 10 recommended).
    progress, cancel : ``progress(done, total)`` over decoded frames; ``cancel()`` true -> Cancelled.

    Returns
    -------
    LensModel with K (px), distortion, image size and the RMS reprojection error (px).

    Raises
    ------
    InputFileError : unreadable video, no board found, or fewer than 5 frames with a board.
    ParameterError : bad corners, square size or n_frames.
    """
    path = Path(path)
    try:
        cols, rows = (int(c) for c in corners)
    except (TypeError, ValueError):
        raise ParameterError(f"calibration.corners: give two whole numbers [columns, rows], got {corners!r}") from None
    if cols < 3 or rows < 3 or cols == rows:
        raise ParameterError(
            f"calibration.corners: {cols} x {rows} inner corners is not usable; count the inner corners "
            "(where four squares meet) along each side, e.g. [9, 6]; they must differ so the board has an orientation"
        )
    if not (square_mm is not None and square_mm > 0):
        raise ParameterError(f"calibration.square_mm: {square_mm!r} mm; give the side of one square, > 0")
    if int(n_frames) < MIN_VIEWS:
        raise ParameterError(
            f"calibration.n_frames: {n_frames} is too few; use at least {MIN_VIEWS} (10 to 20 is good)"
        )
    n_frames = int(n_frames)

    total = _count_frames(path, cancel)
    if total == 0:
        raise InputFileError(f"{path}: no frame could be decoded")
    n_parts = min(n_frames, total)
    # part k holds decoded frames [bounds[k], bounds[k+1])
    bounds = np.linspace(0, total, n_parts + 1).round().astype(int)

    board = np.zeros((rows * cols, 3), np.float32)
    board[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * float(square_mm)

    img_pts: list[np.ndarray] = []
    used: list[int] = []
    size: tuple[int, int] | None = None
    cap = _open(path)
    try:
        part = 0
        for idx in _decoded_frames(cap):
            if cancel is not None and cancel():
                raise Cancelled("calibration cancelled")
            if progress is not None:
                progress(idx + 1, total)
            if idx >= total:
                break
            while part < n_parts - 1 and idx >= bounds[part + 1]:
                part += 1
            if used and used[-1] >= bounds[part]:
                continue  # this part already has its board
            ok, frame = cap.retrieve()
            if not ok or frame is None:
                continue
            gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
            size = (gray.shape[1], gray.shape[0])
            pts = _find_board(gray, (cols, rows))
            if pts is not None:
                img_pts.append(pts)
                used.append(idx)
    finally:
        cap.release()
    if progress is not None:
        progress(total, total)

    if not img_pts:
        raise InputFileError(
            f"{path}: no checkerboard with {cols} x {rows} inner corners was found in any of {total} frames. "
            "Check calibration.corners (count inner corners, where four squares meet) and that the whole board "
            "is in view, sharp and evenly lit"
        )
    if len(img_pts) < MIN_VIEWS:
        raise InputFileError(
            f"{path}: the board ({cols} x {rows} inner corners) was found in only {len(img_pts)} of the "
            f"{n_parts} parts of the video; at least {MIN_VIEWS} are needed. Film the board longer, from more "
            "angles and distances, or raise calibration.n_frames"
        )
    assert size is not None  # set with the first decoded frame, and a board was found in one
    rms, K, dist, per_view = _calibrate(board, img_pts, size)
    # a blurred or mis-ordered detection shows as one view far worse than the others: drop such views
    # (more than 3x the median error and over 1 px) and fit again, as long as enough views remain
    bad = (per_view > 3.0 * np.median(per_view)) & (per_view > 1.0)
    if bad.any() and (~bad).sum() >= MIN_VIEWS:
        img_pts = [p for p, b in zip(img_pts, bad, strict=True) if not b]
        used = [i for i, b in zip(used, bad, strict=True) if not b]
        rms, K, dist, per_view = _calibrate(board, img_pts, size)
    return LensModel(K, dist.ravel()[:5], size, float(rms), used)


def _calibrate(board: np.ndarray, img_pts: list[np.ndarray], size: tuple[int, int]):
    """cv2.calibrateCamera: RMS (px), K, distortion, per-view RMS errors (px)."""
    # the stubs want arrays for the camera matrix and distortion; OpenCV takes None (no initial guess) for outputs
    out = cv2.calibrateCameraExtended([board] * len(img_pts), img_pts, size, None, None)  # type: ignore[call-overload]
    rms, K, dist, per_view = out[0], out[1], out[2], out[-1]
    return float(rms), K, dist, np.asarray(per_view, dtype=float).ravel()


def save_calibration(model: LensModel, path: Path | str) -> None:
    """Write the lens model as TOML (``.toml``) or JSON (any other suffix), atomically."""
    path = Path(path)
    data = model.to_dict()
    if path.suffix.lower() == ".toml":
        blob = tomli_w.dumps({"lens": data}).encode("utf-8")
    else:
        blob = (json.dumps({"lens": data}, indent=2) + "\n").encode("utf-8")
    atomic_write_bytes(path, blob)


def load_calibration(path: Path | str) -> LensModel:
    """Read a lens model written by :func:`save_calibration`.

    Also reads JSON camera configurations that carry ``camera_matrix`` and ``dist_coeffs`` at the top
    level with ``width``/``height`` (pyorc/OpenRiverCam style).

    Raises
    ------
    InputFileError : missing, unreadable or incomplete file, naming what is wrong.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: calibration file not found; check calibration.path or run `fieldtool calibrate`")
    try:
        raw = path.read_bytes()
        data = tomllib.loads(raw.decode("utf-8")) if path.suffix.lower() == ".toml" else json.loads(raw)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError) as e:
        raise InputFileError(f"{path}: not a valid calibration file ({e}); re-run the calibration") from e
    except OSError as e:
        raise InputFileError(f"{path}: cannot be read ({e.strerror})") from e
    if not isinstance(data, dict):
        raise InputFileError(f"{path}: not a valid calibration file (expected a table); re-run the calibration")
    d = data.get("lens", data)
    try:
        K = np.asarray(d["camera_matrix"], dtype=np.float64)
        dist = np.asarray(d["dist_coeffs"], dtype=np.float64).ravel()
        size = d["image_size"] if "image_size" in d else [d["width"], d["height"]]
        size = (int(size[0]), int(size[1]))
        rms = d.get("rms_px")
        rms = None if rms is None else float(rms)
        used = [int(i) for i in d.get("frames_used", [])]
    except KeyError as e:
        raise InputFileError(f"{path}: calibration file lacks {e.args[0]!r}; re-run the calibration") from None
    except (TypeError, ValueError, IndexError) as e:
        raise InputFileError(f"{path}: calibration file has a malformed value ({e}); re-run the calibration") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputFileError(f"{path}: camera_matrix must be a 3x3 matrix with positive focal lengths")
    if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise InputFileError(f"{path}: dist_coeffs must hold 4 or 5 numbers (k1, k2, p1, p2[, k3]), got {dist.size}")
    if size[0] <= 0 or size[1] <= 0:
        raise InputFileError(f"{path}: image_size must be [width, height] in pixels, got {list(size)}")
    return LensModel(K, dist, size, rms, used)
