"""Camera motion in a clip's first frames, seen at its fixed ground points (the GCPs).

A camera held by hand, a tripod that settles or a hovering drone moves the whole picture. The displacement PIV
measures between a pair's frames then carries the camera's, and an unstabilised discharge is wrong by as much
as the camera moved against the surface (a handheld oblique clip read -49 %). The GCPs are fixed ground by their
definition, so a patch of each frame around each GCP is followed from frame 0: corners found in the patch of
frame 0 (``cv2.goodFeaturesToTrack``) are tracked into the same patch of every later frame with pyramidal
Lucas-Kanade (each patch first given frame 0's mean and spread: an exposure step is not motion) and kept where
tracking back lands on the start; the median of their displacements is the point's shift.

What counts as motion is set by the clip, not by a number of pixels fitted to a preset: a point's shift has the
noise of its corners' scatter about it (a fixed patch's corners move together whatever the camera does), and a
point stayed put where its largest shift from frame 0 is within :data:`SIGNIFICANCE` times that noise, or within
:data:`RESOLVED_PX`, what PIV resolves at all. Two points that stayed put say the camera did not move (a moving
camera moves every fixed point; what moved in the other patches is water or an object); where fewer than two
stayed and at least two moved, the camera moved; how far is the median length of the moving points' shifts (a
roll about the centre moves them apart: the median of their shift vectors would read about 0).

Units: px of the frames given (x right, y down); pure numpy and OpenCV, no file, no print.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

#: px: the sub-pixel displacement PIV resolves (the engine's RMS error on uniform shifts and shear in
#: benchmarks/piv_vs_openpiv.py is 0.02-0.07 px): a camera motion below it cannot bias a pair beyond its own noise
RESOLVED_PX = 0.1
#: a point moved where its largest shift from frame 0 exceeds this many of its shift noise (sd), and RESOLVED_PX
SIGNIFICANCE = 5.0
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
    agree: list[int] = field(default_factory=list)  # indices (into the boxes given) of the points that tell: those
    # that stayed put (camera still), or those that moved (camera moved)
    shift_px: list[list[float]] = field(default_factory=list)  # their median shift in each frame from frame 0 (dx, dy)
    moved_px: list[float] = field(default_factory=list)  # the median of their shifts' lengths in each frame
    max_shift_px: float = 0.0  # the largest of those lengths
    noise_px: float = 0.0  # one point's shift noise (sd, the median over points)
    threshold_px: float = RESOLVED_PX  # the shift beyond which a point moved
    moved: bool = False

    def to_dict(self) -> dict:
        return {
            "points": self.points,
            "points_telling": len(self.agree),
            "frames": self.frames,
            "max_shift_px": round(self.max_shift_px, 3),
            "tracking_noise_px": round(self.noise_px, 4),
            "threshold_px": round(self.threshold_px, 3),
            "moved": self.moved,
        }


def _corners(ref: np.ndarray) -> np.ndarray | None:
    """(n, 1, 2) float32 corners of a patch away from its edge (a moved one stays inside), or None: too few."""
    s = ref.shape[0]
    mask = np.zeros(ref.shape, np.uint8)
    m = max(_LK_WIN[0], s // 6)
    mask[m:-m, m:-m] = 255
    pts = cv2.goodFeaturesToTrack(ref, MAX_CORNERS, 0.01, 5, mask=mask, blockSize=5)
    return None if pts is None or len(pts) < MIN_CORNERS else pts.astype(np.float32)


def _row(patches: list[np.ndarray], gap: int) -> np.ndarray:
    """The patches side by side in one image, ``gap`` px of 0 between them: one Lucas-Kanade call a frame for
    every point (half the time of a call per patch); at the pyramid's top the gap keeps the patches apart."""
    h = max(p.shape[0] for p in patches)
    out = np.zeros((h, sum(p.shape[1] + gap for p in patches)), np.uint8)
    x = 0
    for p in patches:
        out[: p.shape[0], x : x + p.shape[1]] = p
        x += p.shape[1] + gap
    return out


def _shifts(patches: list[list[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(K - 1, P, 2) median displacement (px) of the corners of point p's patch in frame 0 in each later frame
    k (NaN where fewer than :data:`MIN_CORNERS` follow), and (K - 1, P) its noise (px): the corners' robust
    scatter about it over the root of their number (a fixed patch's corners move together, whatever the camera
    does: their disagreement is the tracking's own)."""
    refs = patches[0]
    n_pts, gap = len(refs), 4 * _LK_WIN[0]
    out = np.full((len(patches) - 1, n_pts, 2), np.nan)
    noise = np.full((len(patches) - 1, n_pts), np.nan)
    found, owner, x = [], [], 0
    for p, ref in enumerate(refs):
        c = _corners(ref)
        if c is not None:
            found.append(c + np.array([x, 0], np.float32))
            owner.append(np.full(len(c), p))
        x += ref.shape[1] + gap
    if not found:
        return out, noise
    pts, who = np.concatenate(found), np.concatenate(owner)
    ref_row = _row(refs, gap)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.005)
    for k, frame in enumerate(patches[1:]):
        img = _row([_like(raw, ref) for raw, ref in zip(frame, refs, strict=True)], gap)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(
            ref_row, img, pts, None, winSize=_LK_WIN, maxLevel=_LK_LEVELS, criteria=crit
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            img, ref_row, nxt, None, winSize=_LK_WIN, maxLevel=_LK_LEVELS, criteria=crit
        )
        good = (st.ravel() == 1) & (st2.ravel() == 1)
        good &= np.linalg.norm((back - pts).reshape(-1, 2), axis=1) < _FB_MAX_PX
        moved = (nxt - pts).reshape(-1, 2)
        for p in range(n_pts):
            sel = good & (who == p)
            if sel.sum() >= MIN_CORNERS:
                out[k, p] = np.median(moved[sel], axis=0)
                spread = 1.4826 * np.median(np.linalg.norm(moved[sel] - out[k, p], axis=1))
                noise[k, p] = 1.2533 * spread / np.sqrt(sel.sum())  # the median's sd
    return out, noise


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
    d, sd = _shifts(patches)
    seen = np.isfinite(d).all(axis=2).mean(axis=0) >= 0.5  # (P,) points followed in at least half the frames
    if seen.sum() < 2:
        return CameraMotion(points=int(seen.sum()), frames=n_frames)
    idx = np.flatnonzero(seen)
    d, sd = d[:, idx], sd[:, idx]
    noise = float(np.median([np.median(c[np.isfinite(c)]) for c in sd.T]))  # one point's shift noise (px)
    limit = max(RESOLVED_PX, SIGNIFICANCE * noise)
    reach = np.array([np.nanmax(np.linalg.norm(d[:, j], axis=1)) for j in range(len(idx))])  # (P,) px
    still = reach <= limit
    # two fixed points that stayed put say the camera did not move (a moving camera moves every fixed point):
    # what moved there is water or an object in a patch. Otherwise the points that moved give the camera's motion
    group = still if still.sum() >= 2 else ~still
    if group.sum() < 2:
        return CameraMotion(points=len(idx), frames=n_frames, noise_px=noise, threshold_px=limit)
    common = _median_of_finite(d[:, group])
    common = np.where(np.isfinite(common), common, 0.0)
    # how far the points moved, frame by frame: the median of their own shifts' lengths (a roll about the centre
    # moves them apart, and the median of their shift vectors would read about 0)
    far = [
        float(np.median(r[np.isfinite(r)])) if np.isfinite(r).any() else 0.0
        for r in np.linalg.norm(d[:, group], axis=2)
    ]
    biggest = max(far)
    return CameraMotion(
        points=len(idx),
        frames=n_frames,
        agree=[int(i) for i in idx[group]],
        shift_px=[[0.0, 0.0]] + [[round(float(x), 3), round(float(y), 3)] for x, y in common],
        moved_px=[0.0] + [round(v, 3) for v in far],
        max_shift_px=biggest,
        noise_px=noise,
        threshold_px=limit,
        moved=not still.sum() >= 2,
    )


def _median_of_finite(d: np.ndarray) -> np.ndarray:
    """(K, 2) per frame, the median over points of ``d`` (K, P, 2) where the point was followed; NaN where none."""
    out = np.full((d.shape[0], 2), np.nan)
    for k, row in enumerate(d):
        ok = np.isfinite(row).all(axis=1)
        if ok.any():
            out[k] = np.median(row[ok], axis=0)
    return out
