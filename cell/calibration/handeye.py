"""Hand-eye calibration: the camera frame {C} in the tool flange frame {T}, ``T_T_C`` (mm, rad).

Two methods:

* :func:`handeye_from_board_poses` -- the classic AX = XB solvers (Tsai-Lenz, Park-Martin, Daniilidis)
  from flange poses ``T_B_T`` and board poses in the camera ``T_C_Bd`` (from cv2.solvePnP). OpenCV's
  ``cv2.calibrateHandEye`` is used when the installed OpenCV exposes it; the OpenCV 5.0.0 Python wheel does
  not (opencv/opencv#29565, fixed by PR #29584 after the 5.0.0.93 release), so the three closed forms are
  written here as a fallback, following the published algorithms that OpenCV implements.
* :func:`handeye_icp` -- the dissertation's method (4.1.3): scan a gauge of known CAD, find the closest point
of
  every measured point on the CAD triangles (point-to-plane foot points), solve the rigid transform in closed
  form with the unit quaternion (eqs 4.5-4.12, Horn's eigenvector solution) and iterate (eq 4.14) until the
  ratio of successive cost decreases (eq 4.15) says the rest is negligible. With several views the unknown is
  the one ``T_T_C`` shared by all of them, so the closest points are carried back into the flange frame of
  their view and one quaternion solve fits all views (eq 4.3 per view is the single-view special case).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.registration import horn_quaternion
from cell.errors import CalibrationError
from cell.geometry import Pose, invert, make_pose, transform_points

Method = Literal["tsai", "park", "daniilidis"]
_CV_METHODS = {
    "tsai": "CALIB_HAND_EYE_TSAI",
    "park": "CALIB_HAND_EYE_PARK",
    "daniilidis": "CALIB_HAND_EYE_DANIILIDIS",
}
MIN_POSES = 3


def _relative_motions(T_B_T: Sequence[Pose], T_C_Bd: Sequence[Pose]) -> tuple[list[Pose], list[Pose]]:
    """All pairs (i < j): A = T_B_T[j]^-1 T_B_T[i] (flange motion), B = T_C_Bd[j] T_C_Bd[i]^-1 (camera
    motion), so that A X = X B with X = T_T_C (the board is fixed in the base frame)."""
    A, B = [], []
    n = len(T_B_T)
    for i in range(n):
        for j in range(i + 1, n):
            A.append(invert(T_B_T[j]) @ T_B_T[i])
            B.append(T_C_Bd[j] @ invert(T_C_Bd[i]))
    return A, B


def _translation(A: list[Pose], B: list[Pose], R_X: NDArray) -> NDArray:
    """t_X from (R_A - I) t_X = R_X t_B - t_A, stacked over all motions, linear least squares."""
    M = np.vstack([a[:3, :3] - np.eye(3) for a in A])
    rhs = np.concatenate([R_X @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    return np.linalg.lstsq(M, rhs, rcond=None)[0]


def _park(A: list[Pose], B: list[Pose]) -> Pose:
    """Park & Martin (1994): R_X = (M^T M)^(-1/2) M^T with M = sum beta alpha^T of the rotation logs."""
    M = np.zeros((3, 3))
    for a, b in zip(A, B):
        M += np.outer(
            Rotation.from_matrix(b[:3, :3]).as_rotvec(), Rotation.from_matrix(a[:3, :3]).as_rotvec()
        )
    w, V = np.linalg.eigh(M.T @ M)
    R = V @ np.diag(1.0 / np.sqrt(w)) @ V.T @ M.T
    return make_pose(R, _translation(A, B, R))


def _tsai(A: list[Pose], B: list[Pose]) -> Pose:
    """Tsai & Lenz (1989): modified Rodrigues vectors P = 2 sin(theta/2) k; skew(P_A + P_B) P' = P_B - P_A."""
    rows, rhs = [], []
    for a, b in zip(A, B):
        ra, rb = Rotation.from_matrix(a[:3, :3]).as_rotvec(), Rotation.from_matrix(b[:3, :3]).as_rotvec()
        pa = 2 * np.sin(np.linalg.norm(ra) / 2) * ra / max(np.linalg.norm(ra), 1e-15)
        pb = 2 * np.sin(np.linalg.norm(rb) / 2) * rb / max(np.linalg.norm(rb), 1e-15)
        s = pa + pb
        rows.append(np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]]))
        rhs.append(pb - pa)
    p_prime = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    p = 2 * p_prime / np.sqrt(1 + p_prime @ p_prime)
    n = np.linalg.norm(p)
    angle = 2 * np.arcsin(np.clip(n / 2, 0, 1))
    R = Rotation.from_rotvec(angle * p / max(n, 1e-15)).as_matrix()
    return make_pose(R, _translation(A, B, R))


def _qmul(p: NDArray, q: NDArray) -> NDArray:
    """Hamilton product of quaternions stored scalar first (w, x, y, z)."""
    return np.r_[p[0] * q[0] - p[1:] @ q[1:], p[0] * q[1:] + q[0] * p[1:] + np.cross(p[1:], q[1:])]


def _dual_quaternion(T: Pose) -> tuple[NDArray, NDArray]:
    """(real, dual) unit dual quaternion of a rigid motion, scalar first; real part with w >= 0 (so that the
    real scalar parts of A and B, cos(theta/2) of the same screw angle, agree in sign)."""
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    q = np.array([w, x, y, z]) * (1.0 if w >= 0 else -1.0)
    return q, 0.5 * _qmul(np.r_[0.0, T[:3, 3]], q)


def _skew(v: NDArray) -> NDArray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _daniilidis(A: list[Pose], B: list[Pose]) -> Pose:
    """Daniilidis (1999), "Hand-eye calibration using dual quaternions": rotation and translation together.

    With dual quaternions a = x b x^-1 per motion, i.e. a x - x b = 0. Its vector parts are linear in the 8
    unknowns (q, q') of x: [[a - b, [a + b]x, 0, 0], [a' - b', [a' + b']x, a - b, [a + b]x]] (6 rows per
    motion; vector parts of the real and dual parts of a and b). The null space of the stacked matrix is
    spanned by the two right singular vectors of the smallest singular values, v7 and v8; x = l1 v7 + l2 v8
    with the unit constraints q.q = 1 and q.q' = 0 (a quadratic in l1/l2; the root with the larger q.q is
    taken). Written by hand because the installed OpenCV wheel lacks cv2.calibrateHandEye (module doc)."""
    rows = []
    for a, b in zip(A, B):
        (qa, da), (qb, db) = _dual_quaternion(a), _dual_quaternion(b)
        top = np.hstack([(qa - qb)[1:, None], _skew(qa[1:] + qb[1:]), np.zeros((3, 4))])
        bottom = np.hstack(
            [(da - db)[1:, None], _skew(da[1:] + db[1:]), (qa - qb)[1:, None], _skew(qa[1:] + qb[1:])]
        )
        rows += [top, bottom]
    v = np.linalg.svd(np.vstack(rows))[2]
    (u1, v1), (u2, v2) = (v[6, :4], v[6, 4:]), (v[7, :4], v[7, 4:])
    roots = np.roots([u1 @ v1, u1 @ v2 + u2 @ v1, u2 @ v2]).real
    norms = [s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2 for s in roots]
    s = roots[int(np.argmax(norms))]
    l2 = 1.0 / np.sqrt(max(norms))
    q, qd = l2 * (s * u1 + u2), l2 * (s * v1 + v2)
    t = 2 * _qmul(qd, q * np.array([1.0, -1.0, -1.0, -1.0]))[1:]
    return make_pose(Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix(), t)


def handeye_from_board_poses(T_B_T: Sequence[Pose], T_C_Bd: Sequence[Pose], method: Method = "park") -> Pose:
    """``T_T_C`` from N >= 3 flange poses ``T_B_T`` and the board poses ``T_C_Bd`` seen at them (mm).

    The rotations between poses must not all share one axis (then the solution is not unique)."""
    if len(T_B_T) != len(T_C_Bd):
        raise CalibrationError(f"hand-eye: {len(T_B_T)} robot poses but {len(T_C_Bd)} board poses")
    if len(T_B_T) < MIN_POSES:
        raise CalibrationError(
            f"hand-eye: {len(T_B_T)} poses; at least {MIN_POSES} with rotations about "
            "different axes are needed (10-20 recommended)"
        )
    if method not in _CV_METHODS:
        raise CalibrationError(f"hand-eye method '{method}': use one of {sorted(_CV_METHODS)}")
    A, B = _relative_motions(T_B_T, T_C_Bd)
    axes = np.array([Rotation.from_matrix(a[:3, :3]).as_rotvec() for a in A])
    if np.linalg.matrix_rank(axes, tol=1e-3) < 2:
        raise CalibrationError(
            "hand-eye: the robot rotated about a single axis only; add poses that rotate "
            "about at least two different axes"
        )
    solver = getattr(cv2, "calibrateHandEye", None)
    if solver is not None:  # pragma: no cover - depends on the installed OpenCV build
        R, t = solver(
            [g[:3, :3] for g in T_B_T],
            [g[:3, 3] for g in T_B_T],
            [c[:3, :3] for c in T_C_Bd],
            [c[:3, 3] for c in T_C_Bd],
            method=getattr(cv2, _CV_METHODS[method]),
        )
        return make_pose(R, np.ravel(t))
    return {"park": _park, "tsai": _tsai, "daniilidis": _daniilidis}[method](A, B)


# --------------------------------------------------------------------------------------------- ICP method
@dataclass(frozen=True)
class GaugeView:
    """One scan of the gauge: points in the sensor frame {C} (N, 3, mm) and the flange pose ``T_B_T``."""

    points_C: NDArray[np.float64]
    T_B_T: Pose


@dataclass
class IcpHandEyeResult:
    """``T_T_C`` found, the cost Delta_i (eq 4.14, weighted mean squared distance mm^2) and delta (eq 4.15)
    per
    iteration, and whether the stop rule was met before ``max_iter``."""

    T_T_C: Pose
    cost_mm2: list[float] = field(default_factory=list)
    delta: list[float] = field(default_factory=list)
    converged: bool = False

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(self.cost_mm2[-1]))


def _balance(normals: NDArray) -> NDArray:
    """Weights that give every surface orientation (normal binned to ~6 deg) the same total weight: a view
    sees far more of the top face than of the sides, and the sides are what pin the in-plane position."""
    _, inverse, counts = np.unique(
        np.rint(normals * 10).astype(np.int32), axis=0, return_inverse=True, return_counts=True
    )
    return 1.0 / counts[inverse.ravel()]


def handeye_icp(
    nominal: NominalMesh,
    views: Sequence[GaugeView],
    T_W_B: Pose,
    T_W_P: Pose,
    T_T_C_init: Pose,
    max_iter: int = 200,
    rel_tol: float = 1e-6,
    max_dist_mm: float = 1.0,
    start_dist_mm: float = 10.0,
    patience: int = 5,
) -> IcpHandEyeResult:
    """``T_T_C`` by ICP of gauge scans against the gauge CAD ``nominal`` (part frame {P}, mm).

    Each iteration maps the points of view k into {P} with ``T_P_T_k T_T_C`` (T_P_T_k = T_W_P^-1 T_W_B
    T_B_T_k), takes the closest point on the CAD triangles, carries it back into {T} and solves ``T_T_C`` in
    closed form (unit quaternion). Pairs farther apart than a cut-off are left out (table, clutter): the
    cut-off starts at ``start_dist_mm`` (how far off the initial guess may put a point) and follows
    3 x the current RMS down to ``max_dist_mm``. Each surface orientation gets the same total weight
    (:func:`_balance`). Stop rule from eq 4.15: with delta = (D_i - D_i-1)/(D_i-1 - D_i-2) the cost still to
    come is about
    |D_i - D_i-1| delta/(1 - delta) (a geometric tail); stop when that is below ``rel_tol * D_i``; or, at
    the noise floor, where the correspondences only shuffle and delta jumps about, when the lowest cost has
    not improved for ``patience`` iterations (the transform of the lowest cost is returned).
    """
    if not views:
        raise CalibrationError("hand-eye ICP: no gauge scans given")
    T_P_T = [invert(T_W_P) @ T_W_B @ v.T_B_T for v in views]
    pts = [np.asarray(v.points_C, dtype=np.float64).reshape(-1, 3) for v in views]
    if sum(len(p) for p in pts) < 100:
        raise CalibrationError(
            f"hand-eye ICP: only {sum(len(p) for p in pts)} gauge points; scan the gauge "
            "so that it fills the view"
        )
    X = np.array(T_T_C_init, dtype=np.float64)
    result = IcpHandEyeResult(X)
    cutoff = start_dist_mm
    best = (np.inf, X, 0)
    for _ in range(max_iter):
        src, dst, d2, normals = [], [], [], []
        for p_C, T in zip(pts, T_P_T):
            x_P = transform_points(T @ X, p_C)
            em = signed_distance(nominal, x_P)
            keep = np.abs(em.deviation_mm) < cutoff
            src.append(p_C[keep])
            dst.append(transform_points(invert(T), em.closest_mm[keep]))
            d2.append(em.deviation_mm[keep] ** 2)
            normals.append(nominal.face_normals[em.face[keep]])
        d2_all = np.concatenate(d2)
        if len(d2_all) < 100:
            raise CalibrationError(
                f"hand-eye ICP: only {len(d2_all)} points within {cutoff:.1f} mm of the "
                "gauge CAD; the initial hand-eye guess or the gauge placement is too far off"
            )
        w = _balance(np.concatenate(normals))
        result.cost_mm2.append(float(np.sum(w * d2_all) / np.sum(w)))
        c = result.cost_mm2
        cutoff = float(np.clip(3 * np.sqrt(c[-1]), max_dist_mm, cutoff))
        if len(c) >= 3:
            num, den = c[-1] - c[-2], c[-2] - c[-3]
            delta = num / den if den != 0 else 0.0
            result.delta.append(float(delta))
            rest = abs(num) * delta / (1 - delta) if 0 <= delta < 1 else np.inf
            if rest <= rel_tol * c[-1]:
                result.converged = True
                break
        if c[-1] < best[0] * (1 - rel_tol):
            best = (c[-1], X, len(c))
        elif len(c) - best[2] >= patience:  # no progress for `patience` iterations: the noise floor
            result.T_T_C = best[1]
            result.converged = True
            break
        X = horn_quaternion(np.concatenate(src), np.concatenate(dst), w)
        result.T_T_C = X
    return result


def pose_error(T_est: Pose, T_true: Pose) -> tuple[float, float]:
    """(translation error mm, rotation error deg) between two poses."""
    dT = invert(T_true) @ T_est
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(
        np.degrees(np.linalg.norm(Rotation.from_matrix(dT[:3, :3]).as_rotvec()))
    )
