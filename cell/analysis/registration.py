"""Registration of measured clouds into the part frame {P} (dissertation 4.1-4.3), beyond the kinematic chain
(eqs 4.1-4.4), which the inspection composes where it decodes a view.

- :func:`horn_quaternion`: closed-form least-squares rigid transform of point pairs with a unit quaternion
  (Horn 1987; the quaternion model of eqs 4.5-4.7 solved in closed form instead of the iterative 4.9-4.11).
- :func:`datum_align`: 3-2-1 / RPS alignment from measured datum points and their nominal positions.
- :func:`icp_point_to_plane`: ICP on the exact closest points of the nominal mesh, optionally restricted to
  user regions (a boolean mask). Used over the whole part it is *best-fit*, which hides global deviations;
  it is never the default of :func:`cell.analysis.compare.run_compare`.
- :func:`combine_registrations`: the weighted combination of kinematic, datum, feature and ICP estimates
  (eqs 4.21-4.22). Feature-based alignment from curvature labels lives in :mod:`cell.analysis.features`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.errors import ConfigError
from cell.geometry import Pose, make_pose, transform_points


def horn_quaternion(src_mm: ArrayLike, dst_mm: ArrayLike, weights: ArrayLike | None = None) -> Pose:
    """Rigid T minimising sum w |T src - dst|^2 (point pairs, mm), via the unit-quaternion eigenproblem."""
    a = np.asarray(src_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(dst_mm, dtype=np.float64).reshape(-1, 3)
    if len(a) != len(b) or len(a) < 3:
        raise ConfigError(f"point-pair alignment needs >= 3 pairs of equal count, got {len(a)} and {len(b)}")
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    S = ((a - ca) * w[:, None]).T @ (b - cb)
    Sxx, Sxy, Sxz, Syx, Syy, Syz, Szx, Szy, Szz = S.ravel()
    N = np.array(
        [
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ]
    )
    q = np.linalg.eigh(N)[1][:, -1]  # (q0, qx, qy, qz) of the largest eigenvalue
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    return make_pose(R, cb - R @ ca)


def datum_align(measured_mm: ArrayLike, nominal_mm: ArrayLike) -> Pose:
    """``T_P_M``: measured cloud frame into the part frame from datum (RPS) points; >= 3 non-collinear."""
    m = np.asarray(measured_mm, dtype=np.float64).reshape(-1, 3)
    if len(m) >= 3 and np.linalg.matrix_rank(m - m.mean(0), tol=1e-6) < 2:
        raise ConfigError("datum points are collinear: give at least 3 points spanning a plane (3-2-1)")
    return horn_quaternion(m, nominal_mm)


@dataclass(frozen=True)
class IcpResult:
    """``T``: maps the input cloud into the part frame; ``rms_mm`` of point-to-plane residuals at the end."""

    T: Pose
    rms_mm: float
    iterations: int


def icp_point_to_plane(
    nominal: NominalMesh,
    points_mm: ArrayLike,
    T_init: Pose | None = None,
    region: NDArray[np.bool_] | None = None,
    max_iter: int = 30,
    tol_mm: float = 1e-6,
) -> IcpResult:
    """Point-to-plane ICP against exact closest points on the nominal (linearised small-angle step)."""
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if region is not None:
        p = p[np.asarray(region, dtype=bool)]
    if len(p) < 6:
        raise ConfigError(f"ICP needs >= 6 points in the chosen region, got {len(p)}")
    T = np.eye(4) if T_init is None else np.array(T_init, dtype=np.float64)
    rms = np.inf
    for it in range(1, max_iter + 1):
        x = transform_points(T, p)
        em = signed_distance(nominal, x)
        n = nominal.face_normals[em.face]
        r = np.einsum("ij,ij->i", x - em.closest_mm, n)
        A = np.column_stack([np.cross(x, n), n])
        step = np.linalg.lstsq(A, -r, rcond=None)[0]
        T = make_pose(Rotation.from_rotvec(step[:3]).as_matrix(), step[3:]) @ T
        new_rms = float(np.sqrt(np.mean(r * r)))
        if abs(rms - new_rms) < tol_mm and np.linalg.norm(step) < 1e-9 + tol_mm:
            return IcpResult(T, new_rms, it)
        rms = new_rms
    return IcpResult(T, rms, max_iter)


def combine_registrations(
    estimates: Sequence[tuple[Pose, float]],
    centre_mm: ArrayLike,
    nominal_normal: ArrayLike | None = None,
    cloud_normal: ArrayLike | None = None,
) -> Pose:
    """Weighted combination of registrations ``T_P_cloud`` (kinematic, datum, feature, ICP; eqs 4.21-4.22).

    Eq 4.21: the rotation vector is the weighted sum V = sum lambda_i V_i. The V_i are taken relative to the
    most-weighted rotation R_0 (V_i = log(R_0^T R_i), R = R_0 exp(V)): equal to the dissertation's sum for
    nearby rotations and free of the +-pi wrap of raw rotation vectors. Eq 4.22: when the mean surface normals
    of the nominal (part frame) and of the cloud (cloud frame) are given, the angle about the combined axis
    is the one that best aligns them (closed form: the angle between their projections on the plane normal
    to the axis); it is kept from 4.21 when either projection vanishes. The translation (not in the
    dissertation) makes the cloud's ``centre_mm`` land on the weighted mean of where the estimates put it, so
    the result does not depend on the frame origin. Weights (>= 0) are normalised; the dissertation's Table I
    gives user datums the most weight, then features, then the kinematic chain.
    """
    if not estimates:
        raise ConfigError("combine_registrations: no registration estimates")
    Ts = [np.asarray(T, dtype=np.float64) for T, _ in estimates]
    lam = np.array([w for _, w in estimates], dtype=np.float64)
    if (lam < 0).any() or lam.sum() <= 0:
        raise ConfigError(f"combine_registrations: weights must be >= 0 and not all 0, got {lam.tolist()}")
    lam = lam / lam.sum()
    R0 = Ts[int(np.argmax(lam))][:3, :3]
    V = sum(l * Rotation.from_matrix(R0.T @ T[:3, :3]).as_rotvec() for l, T in zip(lam, Ts, strict=True))
    R = R0 @ Rotation.from_rotvec(V).as_matrix()
    if nominal_normal is not None and cloud_normal is not None:
        rv = Rotation.from_matrix(R).as_rotvec()
        if np.linalg.norm(rv) > 1e-12:
            a = rv / np.linalg.norm(rv)
            m = np.asarray(nominal_normal, dtype=np.float64)
            p = np.asarray(cloud_normal, dtype=np.float64)
            m, p = m - a * (a @ m), p - a * (a @ p)
            if np.linalg.norm(m) > 1e-6 * np.linalg.norm(nominal_normal) and np.linalg.norm(
                p
            ) > 1e-6 * np.linalg.norm(cloud_normal):
                theta = np.arctan2(a @ np.cross(p, m), p @ m)
                R = Rotation.from_rotvec(a * theta).as_matrix()
    c = np.asarray(centre_mm, dtype=np.float64)
    target = sum(l * transform_points(T, c) for l, T in zip(lam, Ts, strict=True))
    return make_pose(R, target - R @ c)
