"""Orthorectification: a homography from working-image pixels to the water plane (metres).

World plane axes: right-handed X, Y (m) seen from above (Z up). The working image is the raw
frame, undistorted when a lens model is given; x right, y down (px).

GCP order (thesis figure 7.13): P1, P2, P3, P4 go round the quadrilateral, and
``distances = [L1..L6] = |P1P2|, |P2P3|, |P3P4|, |P4P1|, |P1P3|, |P2P4|``. As in the thesis, P4 is
put at (0, 0) and P1 on the +Y axis; the mirror ambiguity is resolved by keeping the orientation of
the image quadrilateral, and all six distances are then fitted by least squares, so the residual of
the redundant distance is reported.

Velocity vectors are rectified (not the frames): a pixel velocity at a node is mapped to m/s with
the Jacobian of the homography at that node.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from fieldtool.errors import FieldToolError, GeometryError, ParameterError

PAIRS = ((0, 1), (1, 2), (2, 3), (3, 0), (0, 2), (1, 3))  # L1..L6 as index pairs of P1..P4
NAMES = ("L1=|P1P2|", "L2=|P2P3|", "L3=|P3P4|", "L4=|P4P1|", "L5=|P1P3|", "L6=|P2P4|")


@dataclass
class OrthoMapping:
    """Image pixels <-> water-plane metres.

    ``H`` maps homogeneous working-image pixels to world metres. ``residual_m`` is the RMS misfit of
    the GCP distances (or world points) the mapping was built from; ``method`` how it was built.
    """

    H: np.ndarray
    method: str
    residual_m: float = 0.0
    gcp_world: np.ndarray | None = None  # (N, 2) world positions of the GCPs (m)
    details: dict = field(default_factory=dict)

    @property
    def H_inv(self) -> np.ndarray:
        return np.linalg.inv(self.H)

    def image_to_world(self, pts: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) metres."""
        return _apply(self.H, pts)

    def world_to_image(self, pts: np.ndarray) -> np.ndarray:
        """(N, 2) metres -> (N, 2) pixels."""
        return _apply(self.H_inv, pts)

    def jacobian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """d(X, Y)/d(x, y) at pixel positions, shape (..., 2, 2), in m/px."""
        return homography_jacobian(self.H, x, y)

    def rectify_velocity(
        self, x: np.ndarray, y: np.ndarray, u: np.ndarray, v: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixel velocities (px/s) at pixel positions -> world velocities (m/s), same shapes."""
        J = self.jacobian(np.asarray(x, float), np.asarray(y, float))
        U = J[..., 0, 0] * u + J[..., 0, 1] * v
        V = J[..., 1, 0] * u + J[..., 1, 1] * v
        return U, V

    def scale_m_per_px(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Local ground size of one pixel (m/px): sqrt of the Jacobian's determinant."""
        J = self.jacobian(np.asarray(x, float), np.asarray(y, float))
        return np.sqrt(np.abs(np.linalg.det(J)))

    def rectified_image(
        self,
        image: np.ndarray,
        bounds_m: tuple[float, float, float, float] | None = None,
        resolution_m: float | None = None,
        max_side_px: int = 2000,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Warp ``image`` to a north-up map of the water plane.

        Returns the map image and the 3x3 affine ``A`` taking world metres to map pixels
        (column = (X - Xmin) / r, row = (Ymax - Y) / r). ``bounds_m`` = (Xmin, Xmax, Ymin, Ymax);
        default: the image footprint clipped to 3x the GCP extent.
        """
        h, w = image.shape[:2]
        if bounds_m is None:
            corners = self.image_to_world(np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float))
            ref = self.gcp_world if self.gcp_world is not None and len(self.gcp_world) else corners
            c, span = ref.mean(axis=0), np.ptp(ref, axis=0).max() * 1.5 + 1e-9
            lo = np.maximum(corners.min(axis=0), c - span)
            hi = np.minimum(corners.max(axis=0), c + span)
            bounds_m = (lo[0], hi[0], lo[1], hi[1])
        x0, x1, y0, y1 = bounds_m
        if resolution_m is None:
            resolution_m = max(x1 - x0, y1 - y0) / max_side_px
        if not resolution_m > 0:
            raise ParameterError("ortho.resolution_m: must be a positive pixel size in metres")
        A = np.array([[1 / resolution_m, 0, -x0 / resolution_m], [0, -1 / resolution_m, y1 / resolution_m], [0, 0, 1]])
        size = (int(np.ceil((x1 - x0) / resolution_m)) + 1, int(np.ceil((y1 - y0) / resolution_m)) + 1)
        out = cv2.warpPerspective(image, A @ self.H, size, flags=cv2.INTER_LINEAR, borderValue=0)
        return out, A


def homography_jacobian(H: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """d(X, Y)/d(x, y) (m/px) of the homography ``H`` (3, 3) at pixel positions ``x``, ``y``, shape (..., 2, 2).
    ``H`` may be a stack (..., 3, 3) whose leading axes broadcast against ``x`` and ``y`` (one homography per
    Monte Carlo draw)."""
    w = H[..., 2, 0] * x + H[..., 2, 1] * y + H[..., 2, 2]
    X = (H[..., 0, 0] * x + H[..., 0, 1] * y + H[..., 0, 2]) / w
    Y = (H[..., 1, 0] * x + H[..., 1, 1] * y + H[..., 1, 2]) / w
    J = np.empty(np.shape(w) + (2, 2))
    J[..., 0, 0] = (H[..., 0, 0] - X * H[..., 2, 0]) / w
    J[..., 0, 1] = (H[..., 0, 1] - X * H[..., 2, 1]) / w
    J[..., 1, 0] = (H[..., 1, 0] - Y * H[..., 2, 0]) / w
    J[..., 1, 1] = (H[..., 1, 1] - Y * H[..., 2, 1]) / w
    return J


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.asarray(pts, float).reshape(-1, 2)
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:3]


def _signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _circle_point(c: np.ndarray, rc: float, d: np.ndarray, rd: float, names: str) -> tuple[np.ndarray, np.ndarray]:
    """Both intersections of the circles (c, rc) and (d, rd)."""
    dist = float(np.hypot(*(d - c)))
    if rc + rd < dist or abs(rc - rd) > dist:
        raise GeometryError(
            f"ortho.distances_m: {names} cannot form a triangle (each side must be shorter than the sum of the "
            "other two); check the taped distances and their order L1..L6"
        )
    a = (rc**2 - rd**2 + dist**2) / (2 * dist)
    h = np.sqrt(max(rc**2 - a**2, 0.0))
    e = (d - c) / dist
    base = c + a * e
    perp = np.array([-e[1], e[0]])
    return base + h * perp, base - h * perp


def levenberg_marquardt(
    resid: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, max_iter: int = 100, xtol: float = 1e-12
) -> np.ndarray:
    """Unbounded least squares of ``resid`` (m) from ``x0`` (m): Levenberg-Marquardt with a forward-difference
    Jacobian, for the five unknowns of a GCP quadrilateral solved from its distances.

    It stands in for ``scipy.optimize.least_squares`` on the run's critical path: importing scipy.optimize
    costs 0.3-0.5 s of a 5.5 s time to discharge (720p), more than the solve. It reaches the same minimum
    (tests/test_ortho.py: the parameters within 1e-6 m of scipy's, the cost no higher).
    """
    x = np.asarray(x0, float).copy()
    r = resid(x)
    cost = float(r @ r)
    lam = 1e-3
    eye = np.eye(len(x))
    for _ in range(max_iter):
        h = 1e-8 * np.maximum(1.0, np.abs(x))
        J = np.stack([(resid(x + h[i] * eye[i]) - r) / h[i] for i in range(len(x))], axis=1)
        A, g = J.T @ J, J.T @ r
        while True:
            step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
            xn = x + step
            rn = resid(xn)
            cn = float(rn @ rn)
            if cn <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                return x
        x, r, cost, lam = xn, rn, cn, max(lam / 10.0, 1e-12)
        if np.linalg.norm(step) <= xtol * (1.0 + np.linalg.norm(x)):
            break
    return x


def gcp_world_from_distances(gcp_px: np.ndarray, distances: np.ndarray) -> tuple[np.ndarray, float, float]:
    """World coordinates (m) of P1..P4 from the six distances.

    Returns ``(world (4, 2), rms_residual_m, max_residual_m)``; P4 = (0, 0), P1 on +Y.
    """
    L = np.asarray(distances, float)
    if L.shape != (6,):
        raise ParameterError(f"ortho.distances_m: give the six distances L1..L6 in metres, got {len(L)}")
    if np.any(~np.isfinite(L)) or np.any(L <= 0):
        raise ParameterError("ortho.distances_m: every distance must be a positive number of metres")
    px = np.asarray(gcp_px, float)
    if px.shape != (4, 2):
        raise ParameterError(f"ortho.gcp_px: give four [x, y] pixel points P1..P4, got {px.shape[0] if px.ndim else 0}")
    L1, L2, L3, L4, L5, L6 = L
    p4 = np.array([0.0, 0.0])
    p1 = np.array([0.0, L4])
    # P3 from |P3P4| = L3 and |P1P3| = L5 ; P2 from |P1P2| = L1 and |P2P4| = L6
    p3_opts = _circle_point(p4, L3, p1, L5, "L3=|P3P4|, L4=|P4P1|, L5=|P1P3|")
    p2_opts = _circle_point(p1, L1, p4, L6, "L1=|P1P2|, L4=|P4P1|, L6=|P2P4|")
    img_area = _signed_area(px * [1, -1])  # image seen with y up, like the world from above
    best = None
    for p3 in p3_opts:
        for p2 in p2_opts:
            quad = np.array([p1, p2, p3, p4])
            if np.sign(_signed_area(quad)) != np.sign(img_area):
                continue
            err = abs(np.hypot(*(p3 - p2)) - L2)
            if best is None or err < best[0]:
                best = (err, quad)
    if best is None:
        raise GeometryError(
            "ortho.gcp_px: the GCPs do not form a quadrilateral going round P1, P2, P3, P4; check their order"
        )
    quad = best[1]

    def resid(params: np.ndarray) -> np.ndarray:
        q = np.array([[0.0, params[0]], params[1:3], params[3:5], [0.0, 0.0]])
        return np.array([np.hypot(*(q[j] - q[i])) for i, j in PAIRS]) - L

    x = levenberg_marquardt(resid, np.r_[quad[0, 1], quad[1], quad[2]])
    q = np.array([[0.0, x[0]], x[1:3], x[3:5], [0.0, 0.0]])
    if np.sign(_signed_area(q)) != np.sign(img_area):
        raise GeometryError(
            "ortho.distances_m: the distances are inconsistent with the picked GCP order (the fit "
            "flips the quadrilateral)"
        )
    r = resid(x)
    return q, float(np.sqrt(np.mean(r**2))), float(np.max(np.abs(r)))


def check_in_frame(pts: np.ndarray, shape: tuple[int, int] | None, key: str) -> None:
    """GeometryError naming ``key[i]`` when a pixel point lies outside a frame of ``shape`` (H, W)."""
    if shape is None:
        return
    h, w = shape
    bad = [i for i, (x, y) in enumerate(pts) if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5)]
    if bad:
        i = bad[0]
        raise GeometryError(f"{key}[{i}] = ({pts[i][0]:g}, {pts[i][1]:g}) px is outside the {w}x{h} frame")


def from_distances(
    gcp_px,
    distances,
    image_shape: tuple[int, int] | None = None,
    *,
    max_residual_m: float | None = None,
    accept_residual: bool = False,
    frame_shape: tuple[int, int] | None = None,
) -> OrthoMapping:
    """Mapping from 4 GCP pixels and the six distances L1..L6 (m).

    Checked before anything else (see :func:`check_gcp_order`, :func:`check_distance_scale`): the picked
    points must go round a convex quadrilateral, and the distances must be metres. When the largest
    distance residual exceeds ``max_residual_m`` (m) a GeometryError names the distance(s) that most
    likely disagree (see :func:`suspect_distances`; ``frame_shape`` (H, W) puts the principal point at the
    frame centre for that test), unless ``accept_residual``: then ``details["residual_accepted"]`` is set.
    """
    px = np.asarray(gcp_px, float)
    if px.shape != (4, 2):
        raise ParameterError("ortho.gcp_px: give exactly four [x, y] pixel points P1..P4 for method = distances")
    check_in_frame(px, image_shape, "ortho.gcp_px")
    check_distance_scale(distances)
    check_gcp_order(px, distances)
    world, rms, worst = gcp_world_from_distances(px, distances)
    H, _ = cv2.findHomography(px, world, 0)
    if H is None:
        raise GeometryError("ortho.gcp_px: no homography fits these points (are three of them on one line?)")
    details: dict[str, Any] = {"max_distance_residual_m": worst}
    if max_residual_m is not None and worst > max_residual_m:
        sus = suspect_distances(px, distances, world, frame_shape)
        details["suspect_distances"] = sus
        if not accept_residual:
            raise GeometryError(_residual_message(distances, worst, max_residual_m, sus))
        details["residual_accepted"] = True
    return OrthoMapping(H, "distances", rms, world, details)


# ---------------------------------------------------------------------------------------------
# plausibility of the picked GCPs and the taped distances (before any PIV)


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _segments_cross(a, b, c, d) -> bool:
    """Proper intersection of segments ab and cd."""
    d1, d2 = _cross(c, d, a), _cross(c, d, b)
    d3, d4 = _cross(a, b, c), _cross(a, b, d)
    return d1 * d2 < 0 and d3 * d4 < 0


def _lsq_residual(px: np.ndarray, distances) -> float:
    try:
        return gcp_world_from_distances(px, distances)[2]
    except FieldToolError:
        return float("inf")


def check_gcp_order(gcp_px, distances=None) -> None:
    """GeometryError unless P1..P4 go round a convex quadrilateral, as any plane quadrilateral seen by a camera.

    A crossed (bow-tie) pick names the two points that look swapped: of the two swaps that uncross it
    (e.g. P3/P4 or P1/P2), the one whose distances fit best, or both when the distances cannot tell.
    A point inside the triangle of the other three is named too.
    """
    p = np.asarray(gcp_px, float)
    turns = [_cross(p[k], p[(k + 1) % 4], p[(k + 2) % 4]) for k in range(4)]
    if all(t > 0 for t in turns) or all(t < 0 for t in turns):
        return
    order = "; pick them in the order of ortho.distances_m (L1=|P1P2|, L2=|P2P3|, L3=|P3P4|, L4=|P4P1|)"
    cands = None
    if _segments_cross(p[1], p[2], p[3], p[0]):
        what, cands = "the sides P2-P3 and P4-P1 cross", [(2, 3), (0, 1)]
    elif _segments_cross(p[0], p[1], p[2], p[3]):
        what, cands = "the sides P1-P2 and P3-P4 cross", [(1, 2), (3, 0)]
    if cands is None:
        # concave: the vertex whose turn has the minority sign lies inside the others' triangle
        signs = np.sign(turns)
        minority = 1.0 if np.sum(signs > 0) < np.sum(signs < 0) else -1.0
        k = int(np.nonzero(signs == minority)[0][0])
        bad = (k + 1) % 4
        raise GeometryError(
            f"ortho.gcp_px: P{bad + 1} = ({p[bad][0]:.0f}, {p[bad][1]:.0f}) px lies inside the triangle of the other "
            "three GCPs; four points on the water plane seen by a camera always form a convex quadrilateral: "
            f"re-pick P{bad + 1}"
        )
    fits = []
    for i, j in cands:
        q = p.copy()
        q[[i, j]] = q[[j, i]]
        fits.append(_lsq_residual(q, distances) if distances is not None else float("inf"))
    (a1, b1), (a2, b2) = cands
    if np.isfinite(fits[0]) and np.isfinite(fits[1]) and abs(fits[0] - fits[1]) > 0.05 + 0.5 * min(fits):
        i, j = cands[int(np.argmin(fits))]
        swap = f"P{i + 1} and P{j + 1} look swapped"
    else:
        swap = f"P{a1 + 1} and P{b1 + 1} look swapped (or P{a2 + 1} and P{b2 + 1})"
    raise GeometryError(
        f"ortho.gcp_px: the picked points P1..P4 do not go round the quadrilateral ({what}, a bow-tie): {swap}{order}"
    )


def check_distance_scale(distances, max_m: float = 1000.0) -> None:
    """GeometryError when the distances look typed in millimetres (or centimetres) rather than metres."""
    L = np.asarray(distances, float).ravel()
    if len(L) and np.all(np.isfinite(L)) and float(np.max(L)) > max_m:
        raise GeometryError(
            f"ortho.distances_m: the longest distance is {np.max(L):g} m; GCPs around a river "
            f"section are less than {max_m:g} m apart. Were they typed in millimetres? Give metres "
            f"(e.g. {np.max(L) / 1000:g})"
        )


def _camera_misfit(H: np.ndarray, pp: np.ndarray, scale: float) -> float:
    """How far world -> image homography columns are from a pinhole camera with square pixels and its principal
    point at ``pp``, over focal lengths 0.1..10 x ``scale`` (0 = a perfect rigid camera). Dimensionless."""
    G = np.linalg.inv(H)
    G = np.array([[1, 0, -pp[0]], [0, 1, -pp[1]], [0, 0, 1.0]]) @ G
    f = scale * np.logspace(-1, 1, 400)[:, None]
    g1 = np.c_[np.broadcast_to(G[0, 0], f.shape) / f, np.broadcast_to(G[1, 0], f.shape) / f, np.full(f.shape, G[2, 0])]
    g2 = np.c_[np.broadcast_to(G[0, 1], f.shape) / f, np.broadcast_to(G[1, 1], f.shape) / f, np.full(f.shape, G[2, 1])]
    n1, n2 = np.linalg.norm(g1, axis=1), np.linalg.norm(g2, axis=1)
    mis = np.abs(np.sum(g1 * g2, axis=1)) / (n1 * n2) + np.abs(n1 - n2) / (n1 + n2)
    return float(mis.min())


def suspect_distances(
    gcp_px, distances, world: np.ndarray | None = None, frame_shape: tuple[int, int] | None = None
) -> list[dict]:
    """Which distance(s) most likely disagree, best suspect first.

    Six distances fix four plane points with one to spare, so the distances alone cannot tell which one is
    wrong. The picture can: for each Li, the quadrilateral is solved from the other five and its homography
    is compared with a pinhole camera (square pixels, principal point at the frame centre, any focal length);
    the distance whose removal gives the most camera-like quadrilateral is the suspect.

    Returns
    -------
    list of {"name": "L5=|P1P3|", "index": 4, "typed_m": x, "implied_m": y, "camera_misfit": m} sorted by misfit.
    """
    px = np.asarray(gcp_px, float)
    L = np.asarray(distances, float)
    if world is None:
        world = gcp_world_from_distances(px, L)[0]
    if frame_shape is not None:
        pp = np.array([frame_shape[1] - 1, frame_shape[0] - 1], float) / 2.0
        scale = float(max(frame_shape))
    else:
        pp = px.mean(axis=0)
        scale = float(np.ptp(px, axis=0).max() * 2 + 1)
    x0 = np.r_[world[0, 1], world[1], world[2]]
    out: list[dict[str, Any]] = []
    for k in range(6):
        keep = [i for i in range(6) if i != k]

        def resid(params, keep=keep):
            q = np.array([[0.0, params[0]], params[1:3], params[3:5], [0.0, 0.0]])
            return np.array([np.hypot(*(q[PAIRS[i][1]] - q[PAIRS[i][0]])) for i in keep]) - L[keep]

        xs = levenberg_marquardt(resid, x0)
        q = np.array([[0.0, xs[0]], xs[1:3], xs[3:5], [0.0, 0.0]])
        i, j = PAIRS[k]
        implied = float(np.hypot(*(q[j] - q[i])))
        H, _ = cv2.findHomography(px, q, 0)
        mis = _camera_misfit(H, pp, scale) if H is not None else float("inf")
        out.append(
            {
                "name": NAMES[k],
                "index": k,
                "typed_m": float(L[k]),
                "implied_m": implied,
                "camera_misfit": mis + float(np.sqrt(np.mean(resid(xs) ** 2))),
            }
        )
    out.sort(key=lambda d: d["camera_misfit"])
    return out


def _residual_message(distances, worst: float, limit: float, sus: list[dict]) -> str:
    best = sus[0]
    clear = len(sus) > 1 and best["camera_misfit"] < 0.5 * sus[1]["camera_misfit"]
    named = [best] if clear else sus[:2]
    parts = [
        f"{d['name']} (typed {d['typed_m']:g} m, the other five and the picture give {d['implied_m']:.3f} m)"
        for d in named
    ]
    lead = "the suspect is " + parts[0] if clear else "the suspects are " + " or ".join(parts)
    return (
        f"ortho.distances_m: the six distances disagree by up to {worst:.3f} m (limit ortho.max_residual_m = "
        f"{limit:g} m); {lead}. Check the tape and the order L1..L6, or set ortho.accept_residual = true to go on"
    )


def from_world_points(gcp_px, gcp_world, image_shape: tuple[int, int] | None = None) -> OrthoMapping:
    """Mapping from N >= 4 GCP pixels and their plane coordinates [X, Y] (m)."""
    px = np.asarray(gcp_px, float)
    wd = np.asarray(gcp_world, float)
    if px.ndim != 2 or px.shape[1] != 2 or len(px) < 4:
        raise ParameterError("ortho.gcp_px: give at least four [x, y] pixel points")
    if wd.ndim != 2 or wd.shape[1] < 2 or len(wd) != len(px):
        raise ParameterError(f"ortho.gcp_world_m: give one [X, Y] per GCP ({len(px)} GCPs)")
    check_in_frame(px, image_shape, "ortho.gcp_px")
    wd = wd[:, :2]
    H, _ = cv2.findHomography(px, wd, 0)
    if H is None:
        raise GeometryError("ortho.gcp_px: no homography fits these points (are three of them on one line?)")
    res = _apply(H, px) - wd
    return OrthoMapping(H, "world", float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), wd)


def from_two_points(gcp_px, distance_m: float | None = None, gcp_world=None) -> OrthoMapping:
    """Similarity (scale + rotation + shift) from two GCPs, for a camera looking straight down.

    ``gcp_px`` (2, 2) working-image pixels of P1, P2; either the taped ``distance_m`` = |P1P2| (m), giving
    P1 at (0, 0) and P2 on +X, or ``gcp_world`` (2, 2+) their plane coordinates [X, Y] (m). The image is
    seen from above with y flipped (world Y up). Exactly determined: no residual, so a nadir view is
    assumed, not checked (a tilted camera needs 4 GCPs).
    """
    px = np.asarray(gcp_px, float)
    if px.shape != (2, 2) or not np.all(np.isfinite(px)):
        raise ParameterError("ortho.gcp_px: give exactly two [x, y] pixel points P1, P2 for method = two_points")
    z1, z2 = complex(px[0, 0], -px[0, 1]), complex(px[1, 0], -px[1, 1])
    if abs(z2 - z1) < 10.0:
        raise GeometryError(
            f"ortho.gcp_px: P1 and P2 are {abs(z2 - z1):.1f} px apart; pick two points at least 10 px "
            "apart (far apart is better: the scale error is the pick error over this distance)"
        )
    if gcp_world is not None and len(gcp_world):
        wd = np.asarray(gcp_world, float)
        if wd.ndim != 2 or wd.shape[0] != 2 or wd.shape[1] < 2:
            raise ParameterError("ortho.gcp_world_m: give two [X, Y] points (m) for P1, P2")
        w1, w2 = complex(wd[0, 0], wd[0, 1]), complex(wd[1, 0], wd[1, 1])
        if abs(w2 - w1) <= 0:
            raise GeometryError("ortho.gcp_world_m: P1 and P2 are the same point")
    else:
        if distance_m is None or not np.isfinite(distance_m) or not distance_m > 0:
            raise ParameterError("ortho.distances_m: give the taped distance |P1P2| in metres as distances_m = [D]")
        w1, w2 = 0j, complex(float(distance_m), 0.0)
    a = (w2 - w1) / (z2 - z1)
    b = w1 - a * z1
    # world = a * (x - i y) + b  ->  X = Re(a) x + Im(a) y + Re(b), Y = Im(a) x - Re(a) y + Im(b)
    H = np.array([[a.real, a.imag, b.real], [a.imag, -a.real, b.imag], [0.0, 0.0, 1.0]])
    world = _apply(H, px)
    return OrthoMapping(
        H, "two_points", 0.0, world, {"m_per_px": abs(a), "rotation_deg": float(np.degrees(np.angle(a)))}
    )


def from_scale(m_per_px: float) -> OrthoMapping:
    """Uniform scale for a nadir view without GCPs (thesis 8.2): world = scale * (x, -y)."""
    if not m_per_px > 0:
        raise GeometryError("image scale: the section length in pixels must be positive")
    H = np.diag([m_per_px, -m_per_px, 1.0])
    return OrthoMapping(H, "none", 0.0, None, {"m_per_px": m_per_px})


def from_homography(H: np.ndarray, method: str, residual_m: float = 0.0, gcp_world=None, details=None) -> OrthoMapping:
    """Wrap a homography computed elsewhere (e.g. from a full camera pose)."""
    return OrthoMapping(np.asarray(H, float), method, residual_m, gcp_world, details or {})


def check_gcp_residuals(
    mapping: OrthoMapping, gcp_px, max_residual_m: float | None, accept_residual: bool = False
) -> None:
    """World / pose methods: each GCP's miss on the water plane (m) and in the image (px), the worst named.

    Raises GeometryError when the worst miss exceeds ``max_residual_m`` (m) unless ``accept_residual``
    (then ``mapping.details["residual_accepted"]`` is set). Also refuses a mapping that puts a GCP behind
    the camera's horizon. Fills ``details["gcp_residual_m"]`` and ``details["gcp_reprojection_px"]``.
    """
    px = np.asarray(gcp_px, float).reshape(-1, 2)
    world = np.asarray(mapping.gcp_world, float)[:, :2]
    q = np.c_[px, np.ones(len(px))] @ mapping.H.T
    if not (np.all(q[:, 2] > 0) or np.all(q[:, 2] < 0)):
        i = int(np.argmin(np.abs(q[:, 2])))
        raise GeometryError(
            f"ortho.gcp_px: GCP {i + 1} falls beyond the horizon of the others; check the order of "
            "ortho.gcp_px against ortho.gcp_world_m"
        )
    miss_m = np.hypot(*(mapping.image_to_world(px) - world).T)
    if "gcp_residual_m" in mapping.details:  # pose: each GCP met on the plane at its own elevation
        miss_m = np.asarray(mapping.details["gcp_residual_m"], float)
    miss_px = np.hypot(*(mapping.world_to_image(world) - px).T)
    mapping.details.setdefault("gcp_residual_m", [float(v) for v in miss_m])
    mapping.details.setdefault("gcp_reprojection_px", [float(v) for v in miss_px])
    i = int(np.argmax(miss_m))
    if max_residual_m is not None and miss_m[i] > max_residual_m:
        if accept_residual:
            mapping.details["residual_accepted"] = True
            return
        raise GeometryError(
            f"ortho.gcp_world_m: GCP {i + 1} misses by {miss_m[i]:.3f} m on the water plane "
            f"({miss_px[i]:.1f} px in the "
            f"image; limit ortho.max_residual_m = {max_residual_m:g} m); check its pick ortho.gcp_px[{i}] and its "
            "coordinates, or set ortho.accept_residual = true to go on"
        )
