"""Stabilisation: register every frame on the first using stable ground (thesis 7.4).

The user gives where the ground does not move: rectangles ``[x0, y0, x1, y1]`` on fixed features
(the thesis' four regions, e.g. around GCPs), or a polygon around the water, everything outside it
being stable. Corners found there on the reference frame (``cv2.goodFeaturesToTrack``) are followed
into each frame with pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``), always from the
reference frame so errors do not accumulate, starting from the previous frame's registration, and
kept only when tracking back lands on the start (forward-backward check). Both frames are followed with their
local mean and contrast taken out (:func:`_flat`), so that a change of exposure does not lose the features.
A RANSAC homography (or affine map) from the frame to the reference then warps the frame onto the reference. Frames keep
their timestamps: registration changes pixels, never timing.

Stable regions that lie on water show in three ways, each raised as GeometryError: the features
cannot be followed (the surface pattern changes), one region's features disagree with the others
(RANSAC outliers), or all features drift steadily in one direction, as the flow carries them.

Image axes: x right, y down (px), origin at the top-left pixel centre.
"""

from __future__ import annotations

import cv2
import numpy as np

from fieldtool.errors import GeometryError, ParameterError
from fieldtool.processing.masks import check_polygon, check_roi, rasterize

_WIN = (15, 15)  # Lucas-Kanade window (px)
_LEVELS = 3  # pyramid levels above the full image
_FB_MAX_PX = 1.0  # forward-backward error above which a track is dropped (px)
_MIN_FOLLOWED = 0.3  # fraction of the reference features that must be followed and fit the model
_REGION_MIN_INLIER = 0.2  # a region whose features fit the others less often than this is moving
_DRIFT_R2 = 0.9  # share of the feature motion a straight line in time must explain to count as drift
_MIN_FRAMES_FOR_CHECKS = 5
_SCENE_CHECK_EVERY = 10  # frames between two whole-picture checks of a steady drift


def _flat(img: np.ndarray, sigma_px: float = 8.0) -> np.ndarray:
    """``img`` (uint8) less its local mean, over its local rms, both Gaussian of ``sigma_px``, as uint8 about 128
    (32 grey levels a local sd): a change of gain and offset, as an exposure makes, leaves it as it was."""
    f = img.astype(np.float32)
    d = f - cv2.GaussianBlur(f, (0, 0), sigma_px)
    sd = np.sqrt(cv2.GaussianBlur(d * d, (0, 0), sigma_px)) + 1.0
    return np.clip(128.0 + 32.0 * d / sd, 0, 255).astype(np.uint8)


def _to_u8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


class Stabilizer:
    """Registers frames on a reference frame (frame 0) from features on stable ground.

    Parameters
    ----------
    reference : (H, W) gray frame 0 (uint8, or float 0-255).
    regions_px : rectangles [x0, y0, x1, y1] (px) on stable ground (banks, walls, GCPs).
    water_polygon_px : or a polygon [[x, y], ...] (px) around the water; outside it is stable.
    model : "homography" (any camera motion seen on a plane) or "affine" (drone high above).
    max_features : corners detected in the stable area of the reference (shared among the regions).
    ransac_px : RANSAC reprojection threshold (px).
    min_inliers : fewest features that must fit the model in a frame.
    max_drift_px : past this steady drift of the features (px), the picture outside the regions is
        checked: if it stays put while the features drift, they are on water. None = half the
        smallest rectangle side (at least 20 px); not checked with a water polygon alone.

    Raises
    ------
    ParameterError : no stable area given, bad rectangles/polygon or model.
    GeometryError : the stable area has too few trackable corners.
    """

    def __init__(
        self,
        reference: np.ndarray,
        regions_px: list[list[float]] | None = None,
        water_polygon_px: list[list[float]] | None = None,
        model: str = "homography",
        max_features: int = 200,
        ransac_px: float = 2.0,
        min_inliers: int = 12,
        max_drift_px: float | None = None,
        water_box_px: tuple[int, int, int, int] | None = None,
    ) -> None:
        if reference.ndim != 2:
            raise ParameterError(f"stabilize: expected a gray frame (H x W), got shape {reference.shape}")
        if model not in ("homography", "affine"):
            raise ParameterError(f"stabilize.model: {model!r} is not known; use 'homography' or 'affine'")
        regions_px = list(regions_px or [])
        water_polygon_px = list(water_polygon_px or [])
        if not regions_px and not water_polygon_px:
            raise ParameterError(
                "stabilize: give stable regions (stabilize.regions_px, rectangles on fixed ground such as banks or "
                "GCPs) or a polygon around the water (stabilize.water_polygon_px)"
            )
        self.model = model
        self.ransac_px = float(ransac_px)
        self.min_inliers = int(min_inliers)
        h, w = reference.shape
        self.shape = (h, w)
        ref = _to_u8(reference)

        # stable area and the region each pixel belongs to (1-based; 0 = not stable)
        labels = np.zeros((h, w), np.int32)
        sides = []
        for i, rect in enumerate(regions_px):
            x0, y0, x1, y1 = check_roi(rect, (h, w), key=f"stabilize.regions_px[{i}]")
            labels[y0:y1, x0:x1] = i + 1
            sides.append(min(x1 - x0, y1 - y0))
        if not regions_px:
            labels[:] = 1
        if water_polygon_px:
            check_polygon(water_polygon_px, "stabilize.water_polygon_px")
            labels[rasterize((h, w), [water_polygon_px], key="stabilize.water_polygon_px")] = 0
        self.n_regions = max(1, len(regions_px))
        margin = _WIN[0] // 2 + 1
        area = (labels > 0).astype(np.uint8) * 255
        area[:margin], area[-margin:], area[:, :margin], area[:, -margin:] = 0, 0, 0, 0

        # corners per region, so that every region has its share and can be checked on its own
        found, owner = [], []
        for r in range(self.n_regions):
            sub = np.where(labels == r + 1, area, 0).astype(np.uint8)
            p = cv2.goodFeaturesToTrack(
                ref,
                maxCorners=max(1, int(max_features) // self.n_regions),
                qualityLevel=0.01,
                minDistance=7,
                mask=sub,
                blockSize=7,
            )
            if p is not None:
                found.append(p.reshape(-1, 2))
                owner.append(np.full(len(p), r))
        n = sum(len(p) for p in found)
        if n < self.min_inliers:
            where = "stabilize.regions_px" if regions_px else "outside stabilize.water_polygon_px"
            raise GeometryError(
                f"{where}: only {n} trackable corners found on frame 0 (at least {self.min_inliers} needed); "
                "the stable area is too small or too smooth. Draw the regions over textured fixed ground: "
                "stones, posts, walls, GCP markers"
            )
        self.ref_pts = np.concatenate(found).reshape(-1, 1, 2).astype(np.float32)
        self.pt_region = np.concatenate(owner)
        self._ref_flat = _flat(ref)  # the features are followed on frames with their local mean and contrast out
        self._H = np.eye(3)
        self.max_drift_px = (
            (max(20.0, 0.5 * min(sides)) if sides else None) if max_drift_px is None else float(max_drift_px)
        )
        self._check_drift = bool(regions_px) or max_drift_px is not None
        # low-resolution reference and "outside the regions" mask for the drift check: at this scale the
        # shake is a fraction of a pixel while a drift past the limit is several pixels
        self._small_f = max(1.0, min(h, w) / 180.0)
        small = (max(8, round(w / self._small_f)), max(8, round(h / self._small_f)))
        self._small_size = small
        self._ref_small = self._shrink(ref)
        outside = cv2.resize((labels == 0).astype(np.uint8), small, interpolation=cv2.INTER_NEAREST)
        b = 3
        outside[:b], outside[-b:], outside[:, :b], outside[:, -b:] = 0, 0, 0, 0
        if water_box_px is not None:  # the water testifies nothing: it moves by itself, and sun glitter and the
            # sky's reflection stay in the picture when the camera moves (a drifting drone over a glitter column
            # was refused, exit 2, the water's votes outnumbering the banks')
            x0, y0, x1, y1 = (int(round(v / self._small_f)) for v in water_box_px)
            dry = outside.copy()
            dry[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = 0
            if dry.sum() >= 0.05 * outside.size:  # enough fixed ground left to vote
                outside = dry
        self._outside_small = outside.astype(bool)
        self._next_scene_check = 0
        self._region_tracked = np.zeros(self.n_regions)
        self._region_inlier = np.zeros(self.n_regions)
        self._shifts: list[np.ndarray] = []  # per frame: median feature displacement, frame vs reference (px)
        self._res_median: list[float] = []
        self._res_max: list[float] = []
        self._inlier_frac: list[float] = []
        self._shift_max = 0.0

    @property
    def transform(self) -> np.ndarray:
        """3x3 map from the last registered frame's pixels to the reference's pixels."""
        return self._H.copy()

    def _fit(self, src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        if self.model == "homography":
            H, inl = cv2.findHomography(src, dst, cv2.RANSAC, self.ransac_px, maxIters=2000, confidence=0.995)
        else:
            A, inl = cv2.estimateAffine2D(
                src, dst, method=cv2.RANSAC, ransacReprojThreshold=self.ransac_px, maxIters=2000, confidence=0.995
            )
            H = None if A is None else np.vstack([A, [0.0, 0.0, 1.0]])
        inl = np.zeros(len(src), bool) if inl is None else inl.ravel().astype(bool)
        return H, inl

    def register(self, gray: np.ndarray) -> np.ndarray:
        """Warp ``gray`` onto the reference frame (same size and dtype); its time is unchanged.

        Raises
        ------
        GeometryError : the stable features cannot be followed, disagree, or drift like water.
        """
        if gray.shape != self.shape:
            raise ParameterError(
                f"stabilize: frame size {gray.shape[1]}x{gray.shape[0]} differs from frame 0 "
                f"({self.shape[1]}x{self.shape[0]})"
            )
        img = _to_u8(gray)
        n = len(self.ref_pts)
        guess = cv2.perspectiveTransform(self.ref_pts.astype(np.float64), np.linalg.inv(self._H)).astype(np.float32)
        # Lucas-Kanade assumes the brightness stays: an exposure that pumps (a phone's auto-exposure, a cloud) loses
        # the features in the frames as filmed (81 of 200 followed, 198 on the flattened frames)
        nxt, good = self._track(self._ref_flat, _flat(img), guess)
        frame_no = len(self._res_median)
        if good.sum() < max(self.min_inliers, _MIN_FOLLOWED * n):
            raise self._lost(frame_no, int(good.sum()), n)
        src = nxt.reshape(-1, 2)[good]
        dst = self.ref_pts.reshape(-1, 2)[good]
        H, inl = self._fit(src, dst)
        if H is None or inl.sum() < max(self.min_inliers, _MIN_FOLLOWED * n):
            raise self._lost(frame_no, int(inl.sum()), n)

        # residual motion of the stable features after registration (px)
        mapped = cv2.perspectiveTransform(src[inl].reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
        res = np.linalg.norm(mapped - dst[inl], axis=1)
        self._res_median.append(float(np.median(res)))
        self._res_max.append(float(res.max()))
        self._inlier_frac.append(float(inl.sum()) / n)

        self._check_regions(good, inl, frame_no)
        self._check_drift_of(src[inl] - dst[inl], frame_no, img, H)
        self._H = H
        return cv2.warpPerspective(
            gray, H, (self.shape[1], self.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )

    def _track(self, ref: np.ndarray, img: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reference features followed into ``img`` from ``guess`` (px), and which were followed there and
        back to within :data:`_FB_MAX_PX`."""
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(
            ref, img, self.ref_pts, guess, winSize=_WIN, maxLevel=_LEVELS, criteria=crit, flags=flags
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            img, ref, nxt, self.ref_pts.copy(), winSize=_WIN, maxLevel=_LEVELS, criteria=crit, flags=flags
        )
        fb = np.linalg.norm((back - self.ref_pts).reshape(-1, 2), axis=1)
        return nxt, (st.ravel() == 1) & (st2.ravel() == 1) & (fb < _FB_MAX_PX)

    def _lost(self, frame_no: int, kept: int, n: int) -> GeometryError:
        return GeometryError(
            f"stabilize: on frame {frame_no} only {kept} of the {n} stable features of frame 0 could be followed "
            "and agree on one camera motion. The stable regions probably lie on water (its pattern changes and "
            "flows away), are hidden, or the camera moved too far. Draw stabilize.regions_px on fixed, textured "
            "ground (banks, walls, GCP markers), or give stabilize.water_polygon_px"
        )

    def _check_regions(self, good: np.ndarray, inl_of_good: np.ndarray, frame_no: int) -> None:
        if self.n_regions < 2:
            return
        inl = np.zeros_like(good)
        inl[np.flatnonzero(good)[inl_of_good]] = True
        self._region_tracked += np.bincount(self.pt_region[good], minlength=self.n_regions)
        self._region_inlier += np.bincount(self.pt_region[inl], minlength=self.n_regions)
        if frame_no + 1 < _MIN_FRAMES_FOR_CHECKS:
            return
        frac = self._region_inlier / np.maximum(self._region_tracked, 1)
        bad = np.flatnonzero((frac < _REGION_MIN_INLIER) & (self._region_tracked > 0))
        if bad.size:
            i = int(bad[0])
            raise GeometryError(
                f"stabilize.regions_px[{i}]: its features move differently from those of the other regions "
                f"(only {100 * frac[i]:.0f} % agree with them): it lies on water or on something that moves. "
                "Move it onto fixed ground or remove it"
            )

    def _shrink(self, img: np.ndarray) -> np.ndarray:
        small = cv2.resize(img, self._small_size, interpolation=cv2.INTER_AREA).astype(np.float32)
        return cv2.GaussianBlur(small, (0, 0), 1.0)

    def _scene_follows(self, img: np.ndarray, H: np.ndarray) -> bool:
        """Does the image outside the regions move with H (camera motion) rather than stay put (water)?

        Each low-resolution pixel outside the regions votes for the hypothesis that aligns it better
        with the reference: warped by H, or left as it is. Pixels that change anyway (water) abstain.
        """
        f = self._small_f
        S = np.diag([1.0 / f, 1.0 / f, 1.0])
        Hs = S @ H @ np.linalg.inv(S)
        cur = self._shrink(img)
        # the frame's gain and offset matched to the reference's outside the regions (an exposure that changed
        # would otherwise outvote the alignment)
        o = self._outside_small
        x, y = cur[o].astype(np.float64), self._ref_small[o].astype(np.float64)
        if x.size > 2 and x.std() > 0:  # by their mean and sd: a regression would shrink the gain where they moved
            a = float(y.std() / x.std())
            cur = (a * cur + float(y.mean() - a * x.mean())).astype(np.float32)
        warped = cv2.warpPerspective(cur, Hs, self._small_size, flags=cv2.INTER_LINEAR, borderValue=-1)
        e_h = np.abs(warped - self._ref_small)
        e_i = np.abs(cur - self._ref_small)
        use = self._outside_small & (warped >= 0) & (np.abs(e_h - e_i) > 2.0)
        return int((e_h < e_i)[use].sum()) >= int((e_i < e_h)[use].sum())

    def _check_drift_of(self, disp: np.ndarray, frame_no: int, img: np.ndarray, H: np.ndarray) -> None:
        shift = np.median(disp, axis=0)
        self._shifts.append(shift)
        net = float(np.linalg.norm(shift))
        self._shift_max = max(self._shift_max, net)
        if not self._check_drift or self.max_drift_px is None or frame_no + 1 < _MIN_FRAMES_FOR_CHECKS:
            return
        if net <= self.max_drift_px or frame_no < self._next_scene_check:
            return
        # steady drift: a straight line in time explains the motion (shake does not) and carries it past the limit
        d = np.asarray(self._shifts)
        t = np.arange(len(d), dtype=float)
        A = np.c_[np.ones_like(t), t]
        coef, *_ = np.linalg.lstsq(A, d, rcond=None)
        ss_res = float(((d - A @ coef) ** 2).sum())
        ss_tot = float(((d - d.mean(axis=0)) ** 2).sum())
        trend = float(np.linalg.norm(coef[1]) * t[-1])
        if not (ss_tot > 0 and 1 - ss_res / ss_tot >= _DRIFT_R2 and trend > self.max_drift_px):
            return
        # a drifting camera moves the whole picture; water moves only itself
        self._next_scene_check = frame_no + _SCENE_CHECK_EVERY
        if not self._scene_follows(img, H):
            raise GeometryError(
                f"stabilize.regions_px: by frame {frame_no} the stable features have drifted {net:.0f} px steadily "
                "in one direction while the rest of the picture stayed put, as water carried by the flow does. "
                "Draw the regions on fixed ground (banks, walls, GCP markers)"
            )

    def report(self) -> dict:
        """Residual motion of the stable features after registration.

        Returns
        -------
        dict with ``median_px`` (median over frames of the per-frame median residual, px),
        ``max_px`` (largest single-feature residual, px), ``frames`` (frames registered),
        ``min_inlier_fraction`` (worst frame: share of reference features used) and
        ``max_shift_px`` (largest camera motion corrected, px).
        """
        if not self._res_median:
            return {"median_px": None, "max_px": None, "frames": 0, "min_inlier_fraction": None, "max_shift_px": 0.0}
        return {
            "median_px": float(np.median(self._res_median)),
            "max_px": float(np.max(self._res_max)),
            "frames": len(self._res_median),
            "min_inlier_fraction": float(np.min(self._inlier_frac)),
            "max_shift_px": float(self._shift_max),
        }
