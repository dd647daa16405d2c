"""Camera motion in a clip's first frames, seen at its fixed ground points (the GCPs).

A camera held by hand, a tripod that settles or a hovering drone moves the whole picture. The displacement PIV
measures between a pair's frames then carries the camera's, and an unstabilised discharge is wrong by as much
as the camera moved against the surface (a handheld oblique clip read -49 %). The GCPs are fixed ground by their
definition, so a patch of each frame around each GCP is followed from frame 0: corners found in the patch of
frame 0 (``cv2.goodFeaturesToTrack``) are tracked into the same patch of every later frame with pyramidal
Lucas-Kanade (each patch first given frame 0's mean and spread: an exposure step is not motion) and kept where
tracking back lands on the start; the median of their displacements is the point's shift. Where the points
agree, their median is the camera's motion.

What counts as motion is set by the clip, not by a number of pixels fitted to a preset: the points' tracking
noise (how far each point strays from the common shift, robust over the frames; px), divided by the root of the
points that agree, is the noise of the common shift. The camera moved where its largest shift from frame 0 is
both :data:`SIGNIFICANCE` times that noise and more than :data:`RESOLVED_PX`, what PIV resolves at all.

Units: px of the frames given (x right, y down); pure numpy and OpenCV, no file, no print.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

#: px: the sub-pixel displacement PIV resolves (the engine's RMS error on uniform shifts and shear in
#: benchmarks/piv_vs_openpiv.py is 0.02-0.07 px): a camera motion below it cannot bias a pair beyond its own noise
RESOLVED_PX = 0.1
#: the common shift must exceed this many of its own noise (sd) to count as motion
SIGNIFICANCE = 5.0
#: a point agrees with the common shift where it strays from it by at most this many tracking-noise sd
AGREE_SD = 3.0
#: corners sought per patch; fewer than MIN_CORNERS followed and the point says nothing for that frame
MAX_CORNERS = 24
MIN_CORNERS = 4
#: Lucas-Kanade window (px) and pyramid levels above the patch
_LK_WIN = (11, 11)
_LK_LEVELS = 2
#: forward-backward error (px) above which a corner's track is dropped
_FB_MAX_PX = 0.5


def patch_side(shape: tuple[int, int]) -> int:
    """The side (px) of the patch followed around each point: a tenth of the frame's short side, 48 to 256 px
    (a GCP marker and the ground beside it; the patch scales with the frame, not with a camera we drew)."""
    return int(np.clip(round(min(shape) / 10), 48, 256))


def patch_boxes(points_px, shape: tuple[int, int], side: int | None = None) -> list[tuple[int, int, int, int]]:
    """(x0, y0, x1, y1) px of the patch around each point of ``points_px`` ([[x, y], ...]) that lies whole in a
    frame of ``shape`` (H, W); points too near the edge or outside get no patch (they are left out)."""
    h, w = int(shape[0]), int(shape[1])
    s = patch_side(shape) if side is None else int(side)
    boxes = []
    for p in points_px or []:
        x, y = float(p[0]), float(p[1])
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        x0, y0 = int(round(x)) - s // 2, int(round(y)) - s // 2
        if x0 < 0 or y0 < 0 or x0 + s > w or y0 + s > h:
            continue
        boxes.append((x0, y0, x0 + s, y0 + s))
    return boxes


@dataclass
class CameraMotion:
    """What the fixed points say about the camera over the frames looked at (px of the frames)."""

    points: int  # points followed (patches with enough corners on frame 0)
    frames: int  # frames looked at, frame 0 included
    agree: list[int] = field(default_factory=list)  # indices (into the boxes given) of the points that move together
    shift_px: list[list[float]] = field(default_factory=list)  # the common shift of each frame from frame 0 (dx, dy)
    max_shift_px: float = 0.0  # the largest common shift from frame 0
    noise_px: float = 0.0  # one point's tracking noise (sd)
    threshold_px: float = RESOLVED_PX  # what the largest shift had to exceed to count as motion
    moved: bool = False

    def to_dict(self) -> dict:
        return {
            "points": self.points,
            "points_agreeing": len(self.agree),
            "frames": self.frames,
            "max_shift_px": round(self.max_shift_px, 3),
            "tracking_noise_px": round(self.noise_px, 4),
            "threshold_px": round(self.threshold_px, 3),
            "moved": self.moved,
        }


def _shifts(ref: np.ndarray, frames: list[np.ndarray]) -> np.ndarray:
    """(K, 2) median displacement (px) of ``ref``'s corners in each of ``frames`` (NaN where too few follow)."""
    out = np.full((len(frames), 2), np.nan)
    s = ref.shape[0]
    mask = np.zeros(ref.shape, np.uint8)
    m = max(_LK_WIN[0], s // 6)  # corners away from the edge, so that a moved one stays inside the patch
    mask[m:-m, m:-m] = 255
    pts = cv2.goodFeaturesToTrack(ref, MAX_CORNERS, 0.01, 5, mask=mask, blockSize=5)
    if pts is None or len(pts) < MIN_CORNERS:
        return out
    pts = pts.astype(np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.005)
    for k, raw in enumerate(frames):
        img = _like(raw, ref)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(ref, img, pts, None, winSize=_LK_WIN, maxLevel=_LK_LEVELS, criteria=crit)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            img, ref, nxt, None, winSize=_LK_WIN, maxLevel=_LK_LEVELS, criteria=crit
        )
        good = (st.ravel() == 1) & (st2.ravel() == 1)
        good &= np.linalg.norm((back - pts).reshape(-1, 2), axis=1) < _FB_MAX_PX
        if good.sum() >= MIN_CORNERS:
            out[k] = np.median((nxt - pts).reshape(-1, 2)[good], axis=0)
    return out


def _like(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``img`` with the mean and spread of ``ref`` (uint8): Lucas-Kanade assumes the brightness stays, and an
    auto-exposure or white-balance step changes a patch's gain and offset (the exposure scenes' still cameras read
    0.09-0.14 px of motion against 0.03 px with this)."""
    f = img.astype(np.float32)
    m, s = cv2.meanStdDev(f)
    m0, s0 = cv2.meanStdDev(ref)
    out = (f - float(m[0, 0])) * (float(s0[0, 0]) / max(float(s[0, 0]), 1e-6)) + float(m0[0, 0])
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def measure(patches: list[list[np.ndarray]]) -> CameraMotion:
    """The camera's motion from ``patches[k][p]``: the grey patch (uint8, the same box in every frame) of point
    p in frame k, frame 0 first. See the module's docstring."""
    n_frames = len(patches)
    n_pts = len(patches[0]) if n_frames else 0
    if n_frames < 3 or n_pts < 2:
        return CameraMotion(points=0, frames=n_frames)
    d = np.stack([_shifts(patches[0][p], [patches[k][p] for k in range(1, n_frames)]) for p in range(n_pts)], 1)
    seen = np.isfinite(d).all(axis=2).mean(axis=0) >= 0.5  # (P,) points followed in at least half the frames
    if seen.sum() < 2:
        return CameraMotion(points=int(seen.sum()), frames=n_frames)
    idx = np.flatnonzero(seen)
    d = d[:, idx]
    common = _median_of_finite(d)  # (K, 2)
    stray = np.linalg.norm(d - common[:, None], axis=2)  # (K, P), NaN where a point or the frame says nothing
    per_point = np.array([np.median(c[np.isfinite(c)]) for c in stray.T])  # (P,): each seen in half the frames
    noise = float(1.4826 * np.median(per_point))
    agree = idx[per_point <= AGREE_SD * noise + 1e-9] if noise > 0 else idx
    if len(agree) < 2:
        return CameraMotion(points=len(idx), frames=n_frames, noise_px=noise)
    common = _median_of_finite(d[:, np.isin(idx, agree)])
    common = np.where(np.isfinite(common), common, 0.0)
    mag = np.linalg.norm(common, axis=1)
    threshold = max(RESOLVED_PX, SIGNIFICANCE * noise / np.sqrt(len(agree)))
    biggest = float(mag.max()) if len(mag) else 0.0
    return CameraMotion(
        points=len(idx),
        frames=n_frames,
        agree=[int(i) for i in agree],
        shift_px=[[0.0, 0.0]] + [[round(float(x), 3), round(float(y), 3)] for x, y in common],
        max_shift_px=biggest,
        noise_px=noise,
        threshold_px=float(threshold),
        moved=biggest > threshold,
    )


def _median_of_finite(d: np.ndarray) -> np.ndarray:
    """(K, 2) per frame, the median over points of ``d`` (K, P, 2) where the point was followed; NaN where none."""
    out = np.full((d.shape[0], 2), np.nan)
    for k, row in enumerate(d):
        ok = np.isfinite(row).all(axis=1)
        if ok.any():
            out[k] = np.median(row[ok], axis=0)
    return out
