"""Full camera pose from 6 or more ground control points with X, Y, Z (beyond the thesis).

As RIVeR and pyorc do for fixed cameras: with known intrinsics (calibrated, or given), the pose
(rotation, translation) is solved from GCP pixels and their surveyed world coordinates with
``cv2.solvePnP`` and refined by Levenberg-Marquardt. The water surface is then the plane Z = level,
and :func:`plane_homography` maps undistorted image pixels onto it.

World coordinates may be large projected coordinates (e.g. EPSG:28992, 10⁵ m): a local origin
(the mean of the GCPs) is subtracted internally for numerical conditioning and kept in the Pose.
World axes: X, Y horizontal, Z up (m). Image axes: x right, y down (px).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fieldtool.errors import GeometryError, ParameterError

MIN_GCPS = 6


@dataclass(eq=False)  # holds arrays: compare fields explicitly
class Pose:
    """Camera pose in a local world frame.

    A world point P (m) projects as ``K · dist(R · (P - origin) + tvec)``.

    Attributes
    ----------
    rvec, tvec : (3,) Rodrigues rotation and translation (m) from local world to camera frame.
    camera_matrix : (3, 3) K (px).
    dist_coeffs : (n,) distortion coefficients, OpenCV order.
    reprojection_px : (N,) distance between each GCP's pixel and its reprojected world position (px).
    rms_px : RMS of ``reprojection_px`` (px).
    origin : (3,) world coordinates of the local origin (m).
    """

    rvec: np.ndarray
    tvec: np.ndarray
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    reprojection_px: np.ndarray
    rms_px: float
    origin: np.ndarray

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation matrix world -> camera."""
        return cv2.Rodrigues(np.asarray(self.rvec, float))[0]

    def camera_position(self) -> np.ndarray:
        """(3,) camera centre in world coordinates (m)."""
        R = self.rotation
        return self.origin - R.T @ np.asarray(self.tvec, float).ravel()

    def project(self, world: np.ndarray) -> np.ndarray:
        """(N, 3) world points (m) -> (N, 2) raw (distorted) pixels."""
        local = np.asarray(world, float).reshape(-1, 3) - self.origin
        px, _ = cv2.projectPoints(local.reshape(-1, 1, 3), self.rvec, self.tvec, self.camera_matrix, self.dist_coeffs)
        return px.reshape(-1, 2)


def _as_points(a, cols: int, key: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != cols:
        what = "[x, y] pixels" if cols == 2 else "[X, Y, Z] metres"
        raise ParameterError(f"{key}: expected a list of {what}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{key}: contains a value that is not a number")
    return arr


def solve_pose(
    gcp_px: np.ndarray, gcp_world: np.ndarray, camera_matrix: np.ndarray, dist_coeffs: np.ndarray | None = None
) -> Pose:
    """Solve the camera pose from 6+ GCPs.

    Parameters
    ----------
    gcp_px : (N, 2) GCP positions in the raw frame (px); distortion is handled by ``dist_coeffs``.
    gcp_world : (N, 3) their surveyed X, Y, Z (m), any projected datum.
    camera_matrix : (3, 3) K (px).
    dist_coeffs : distortion coefficients (OpenCV order) or None for none.

    Returns
    -------
    Pose, with per-point reprojection errors (px) and their RMS.

    Raises
    ------
    ParameterError : fewer than 6 GCPs, mismatched counts, bad shapes.
    GeometryError : GCPs on one line, no solution, or GCPs behind the camera.
    """
    px = _as_points(gcp_px, 2, "ortho.gcp_px")
    world = _as_points(gcp_world, 3, "ortho.gcp_world_m")
    if len(px) != len(world):
        raise ParameterError(
            f"ortho.gcp_px has {len(px)} points but ortho.gcp_world_m has {len(world)}; give one X, Y, Z per pixel"
        )
    if len(px) < MIN_GCPS:
        raise ParameterError(
            f"ortho.gcp_world_m: the camera pose needs at least {MIN_GCPS} GCPs with X, Y, Z, got {len(px)}; "
            "with 4 GCPs use ortho.method = 'world' or 'distances'"
        )
    K = np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
    dist = np.zeros(5) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64).ravel()
    origin = world.mean(axis=0)
    local = world - origin
    sv = np.linalg.svd(local - local.mean(axis=0), compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1e-12):
        raise GeometryError("ortho.gcp_world_m: the GCPs lie on one line; spread them over both banks")

    obj = local.reshape(-1, 1, 3)
    img = px.reshape(-1, 1, 2)
    best = None
    for flag in (cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_ITERATIVE, cv2.SOLVEPNP_EPNP):
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=flag)
        except cv2.error:
            continue
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
        err = _reprojection(obj, px, rvec, tvec, K, dist)
        depth = (cv2.Rodrigues(rvec)[0] @ local.T + tvec.reshape(3, 1))[2]
        if np.any(depth <= 0):
            continue
        rms = float(np.sqrt(np.mean(err**2)))
        if best is None or rms < best[0]:
            best = (rms, rvec.ravel(), tvec.ravel(), err)
    if best is None:
        raise GeometryError(
            "ortho.gcp_px / ortho.gcp_world_m: no camera pose puts all GCPs in front of the camera; check that "
            "each pixel is paired with the right X, Y, Z and that the camera matrix belongs to this video"
        )
    rms, rvec, tvec, err = best
    return Pose(rvec, tvec, K, dist, err, rms, origin)


def _reprojection(obj, px, rvec, tvec, K, dist) -> np.ndarray:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - px, axis=1)


def plane_homography(pose: Pose, level_z: float) -> np.ndarray:
    """3x3 homography from UNDISTORTED image pixels to world (X, Y) (m) on the plane Z = level_z.

    Undistorted pixels are those of :meth:`LensModel.undistort_points` / ``cv2.undistortPoints``
    with ``P = K`` (same camera matrix). World X, Y are in the frame of ``gcp_world``.

    Raises
    ------
    GeometryError : the camera is not above the plane, or the plane is seen edge-on.
    """
    R = pose.rotation
    t = np.asarray(pose.tvec, float).ravel()
    z0 = float(level_z) - float(pose.origin[2])
    cam = pose.camera_position()
    if cam[2] <= level_z:
        raise GeometryError(
            f"water_level: the level {level_z:.3f} m is not below the camera ({cam[2]:.3f} m by the GCP pose); "
            "check the level's datum against the GCPs' Z"
        )
    # local plane (X, Y, 1) -> pixels
    G = pose.camera_matrix @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * z0 + t])
    if abs(np.linalg.det(G)) < 1e-12 * np.abs(G).max() ** 3:
        raise GeometryError("water_level: the water plane is seen edge-on from the camera; no mapping exists")
    T = np.array([[1.0, 0.0, pose.origin[0]], [0.0, 1.0, pose.origin[1]], [0.0, 0.0, 1.0]])
    H = T @ np.linalg.inv(G)
    return H / H[2, 2]


MIN_GCPS_LENS = 8


def _lens_K(f: float, cx: float, cy: float) -> np.ndarray:
    """Camera matrix (px) of square pixels with focal length ``f`` and principal point ``(cx, cy)`` (px)."""
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def _lens_first_guess(obj: np.ndarray, px: np.ndarray, w: int, cx: float, cy: float) -> tuple | None:
    """The undistorted pose that best reprojects the GCPs over fields of view of 20-140 degrees:
    ``(rms px, [f px, k1 = 0, rvec (3,), tvec (3,) m])``, or None when no pose is found.
    ``obj`` (N, 1, 3) GCPs (m, about their mean), ``px`` (N, 2) pixels, ``w`` the frame's width (px)."""
    best = None
    for fov in np.arange(20.0, 141.0, 5.0):
        f0 = (w / 2.0) / np.tan(np.radians(fov) / 2.0)
        K0 = _lens_K(f0, cx, cy)
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, px.reshape(-1, 1, 2), K0, np.zeros(5), flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error:
            continue
        if not ok:
            continue
        err = _reprojection(obj, px, rvec, tvec, K0, np.zeros(5))
        rms = float(np.sqrt(np.mean(err**2)))
        if best is None or rms < best[0]:
            best = (rms, np.r_[f0, 0.0, rvec.ravel(), tvec.ravel()])
    return best


def _lens_sigmas(
    J: np.ndarray, sigma: float, px: np.ndarray, cx: float, cy: float, f: float, with_k2: bool
) -> tuple[float, float, float]:
    """How well the GCPs constrain the lens: ``(rc, sigma_f, sigma_shift)``, rc the outermost GCP's radius
    over the focal length (1), sigma_f the focal length's 1-sigma (px) and sigma_shift the distortion's radial
    shift 1-sigma at that GCP (px; beyond it the fit is an extrapolation), both inf when J is singular.
    ``J`` the least-squares Jacobian (parameters f, k1, rvec, tvec[, k2]), ``sigma`` a pick's 1-sigma (px)."""
    rc = float(np.max(np.hypot(px[:, 0] - cx, px[:, 1] - cy))) / f
    g = np.r_[f * rc**3, f * rc**5] if with_k2 else np.r_[f * rc**3]
    k_idx = [1, 8] if with_k2 else [1]
    try:
        cov = np.linalg.inv(J.T @ J) * sigma**2
        sf = float(np.sqrt(cov[0, 0]))
        s_edge = float(np.sqrt(g @ cov[np.ix_(k_idx, k_idx)] @ g))
    except np.linalg.LinAlgError:
        sf, s_edge = float("inf"), float("inf")
    return rc, sf, s_edge


def fit_lens(
    gcp_px: np.ndarray,
    gcp_world: np.ndarray,
    image_size: tuple[int, int],
    *,
    pixel_sigma_px: float = 1.0,
    max_rel_sigma_f: float = 0.03,
    max_sigma_shift_px: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, Pose, dict]:
    """Focal length and first radial distortion from 8+ GCPs, with the pose (as pyorc's
    ``optimize_intrinsic``), for a camera that has no checkerboard calibration.

    Model: square pixels, principal point at the image centre, ``dist = (k1, k2, 0, 0, 0)``; k2 is fitted
    only from 10 GCPs on (else 0). The focal length is first searched over fields of view of 20-140
    degrees with an undistorted pose, then focal length, distortion and the pose are refined together by
    least squares on the reprojection.

    Parameters
    ----------
    gcp_px : (N, 2) GCP pixels in the raw (distorted) frame.
    gcp_world : (N, 3) surveyed X, Y, Z (m).
    image_size : (width, height) of the frame (px).
    pixel_sigma_px : 1-sigma of a GCP pick (px), a floor for the fit's own residual.
    max_rel_sigma_f, max_sigma_shift_px : the fit is refused when the GCPs leave the focal length
        (relative 1-sigma) or the distortion's radial shift at the outermost GCP (1-sigma, px) less
        constrained than this.

    Returns
    -------
    (K (3, 3) px, dist (5,), Pose, report) with report ``f_px, k1, k2, sigma_f_px,
    sigma_shift_px, gcp_radius_px, rms_px, reprojection_px`` (per GCP).

    Raises
    ------
    ParameterError : fewer than 8 GCPs, shapes.
    GeometryError : no pose, or the GCPs cannot constrain the lens (e.g. all near the image centre).
    """
    px = _as_points(gcp_px, 2, "ortho.gcp_px")
    world = _as_points(gcp_world, 3, "ortho.gcp_world_m")
    if len(px) != len(world):
        raise ParameterError(
            f"ortho.gcp_px has {len(px)} points but ortho.gcp_world_m has {len(world)}; give one X, Y, Z per pixel"
        )
    if len(px) < MIN_GCPS_LENS:
        raise ParameterError(
            f"ortho.fit_lens: fitting the lens needs at least {MIN_GCPS_LENS} GCPs with X, Y, Z, got "
            f"{len(px)}; calibrate with a checkerboard video instead (calibration.path)"
        )
    w, h = int(image_size[0]), int(image_size[1])
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    origin = world.mean(axis=0)
    obj = (world - origin).reshape(-1, 1, 3)

    def K_of(f: float) -> np.ndarray:
        return _lens_K(f, cx, cy)

    best = _lens_first_guess(obj, px, w, cx, cy)
    if best is None:
        raise GeometryError(
            "ortho.fit_lens: no camera pose fits these GCPs; check that each pixel is paired with its X, Y, Z"
        )

    with_k2 = len(px) >= 10

    def unpack(q: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        dist = np.array([q[1], q[8] if with_k2 else 0.0, 0, 0, 0])
        return q[0], dist, q[2:5], q[5:8]

    def resid(q: np.ndarray) -> np.ndarray:
        f, dist, rv, tv = unpack(q)
        proj, _ = cv2.projectPoints(obj, rv, tv, K_of(f), dist)
        return (proj.reshape(-1, 2) - px).ravel()

    q0 = np.r_[best[1], 0.0] if with_k2 else best[1]
    scale = np.r_[best[1][0], 0.1, np.ones(6), [0.1] if with_k2 else []]
    from scipy.optimize import least_squares  # lazy: scipy.optimize costs 0.2-0.3 s to import; only a lens fit

    sol = least_squares(resid, q0, x_scale=scale, method="lm")
    q = sol.x
    r = resid(q).reshape(-1, 2)
    err = np.linalg.norm(r, axis=1)
    rms = float(np.sqrt(np.mean(err**2)))
    n_obs, n_par = r.size, len(q)
    sigma = max(float(np.sqrt(np.sum(r**2) / max(n_obs - n_par, 1))), float(pixel_sigma_px))
    J = sol.jac
    f, dist, rv, tv = unpack(q)
    f, k1 = float(f), float(dist[0])
    # how well the distortion is known over the part of the frame the GCPs span: its radial shift (px)
    # at the farthest GCP from the centre (beyond it the fit is an extrapolation, and says so)
    rc, sf, s_edge = _lens_sigmas(J, sigma, px, cx, cy, f, with_k2)
    report = {
        "f_px": f,
        "k1": k1,
        "k2": float(dist[1]),
        "sigma_f_px": sf,
        "sigma_shift_px": s_edge,
        "gcp_radius_px": float(rc * f),
        "rms_px": rms,
        "reprojection_px": [float(e) for e in err],
        "n_gcps": int(len(px)),
    }
    if not (f > 0) or not np.isfinite(sf) or sf / f > max_rel_sigma_f or s_edge > max_sigma_shift_px:
        raise GeometryError(
            f"ortho.fit_lens: these {len(px)} GCPs cannot constrain the lens (focal length {f:.0f} ± {sf:.0f} px, "
            f"distortion at the outermost GCP known to ± {s_edge:.1f} px; needed: ± {100 * max_rel_sigma_f:.0f} % and "
            f"± {max_sigma_shift_px:g} px); add GCPs near the image corners and at several distances, or calibrate "
            "with a checkerboard video"
        )
    depth = (cv2.Rodrigues(rv)[0] @ obj.reshape(-1, 3).T + tv.reshape(3, 1))[2]
    if np.any(depth <= 0):
        raise GeometryError("ortho.fit_lens: the fitted camera has GCPs behind it; check the GCP pairing")
    K = K_of(f)
    return K, dist, Pose(rv.copy(), tv.copy(), K, dist, err, rms, origin), report
