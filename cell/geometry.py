"""Rigid transforms as 4x4 float64 matrices named ``T_<to>_<from>`` (mm, rad).

``T_B_T @ p_T`` maps a homogeneous point from the tool frame {T} into the base frame {B}.
SciPy's Rotation does the rotation algebra; these helpers only fix the cell's conventions. It is imported by
the functions that use it (scipy.spatial costs about 0.4 s of CPU to import): the config schemas import this
module for their types, and a command that only reads a config should not pay for it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

Pose = NDArray[np.float64]


def _rotation() -> type[Rotation]:
    from scipy.spatial.transform import Rotation

    return Rotation


def make_pose(rotation: ArrayLike | None = None, translation_mm: ArrayLike | None = None) -> Pose:
    """Build T from a 3x3 rotation matrix and a translation in mm."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = np.asarray(rotation, dtype=np.float64)
    if translation_mm is not None:
        T[:3, 3] = np.asarray(translation_mm, dtype=np.float64)
    return T


def pose_from_xyz_rpy(xyz_mm: ArrayLike, rpy_rad: ArrayLike) -> Pose:
    """Pose from a translation (mm) and fixed-axis roll, pitch, yaw (rad): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return make_pose(_rotation().from_euler("xyz", np.asarray(rpy_rad, dtype=np.float64)).as_matrix(), xyz_mm)


def pose_from_xyz_rotvec(xyz_mm: ArrayLike, rotvec_rad: ArrayLike) -> Pose:
    """Pose from a translation (mm) and a rotation vector (axis * angle, rad), as UR controllers use."""
    return make_pose(_rotation().from_rotvec(np.asarray(rotvec_rad, dtype=np.float64)).as_matrix(), xyz_mm)


def pose_to_xyz_rotvec(T: Pose) -> NDArray[np.float64]:
    """Inverse of :func:`pose_from_xyz_rotvec`: a 6-vector [x, y, z (mm), rx, ry, rz (rad)]."""
    return np.concatenate([T[:3, 3], _rotation().from_matrix(T[:3, :3]).as_rotvec()])


def invert(T: Pose) -> Pose:
    """Inverse of a rigid transform without a general matrix inverse."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: NDArray[np.floating[Any]], points: ArrayLike) -> NDArray[np.float64]:
    """Apply T to an (..., 3) array of points."""
    p = np.asarray(points, dtype=np.float64)
    # einsum, not p @ R.T: numpy's matmul on (N, 3) x (3, 3) is several times slower here (and rounds
    # otherwise); the translation added in place: the same sums without a second (N, 3) array
    out: NDArray[np.float64] = np.einsum("...j,ij->...i", p, T[:3, :3])
    out += T[:3, 3]
    return out


def transform_vectors(T: Pose, vectors: ArrayLike) -> NDArray[np.float64]:
    """Rotate an (..., 3) array of direction vectors by T (no translation)."""
    return np.einsum("...j,ij->...i", np.asarray(vectors, dtype=np.float64), T[:3, :3])


def look_at(eye_mm: ArrayLike, target_mm: ArrayLike, up: ArrayLike = (0.0, 1.0, 0.0)) -> Pose:
    """Pose of an optical frame at ``eye`` whose +z axis points at ``target``.

    The optical frame follows OpenCV: +z forward, +x right, +y down in the image. ``up`` is the world
    direction that should appear as image-up (-y); it is replaced by a perpendicular one if parallel to z.
    """
    eye = np.asarray(eye_mm, dtype=np.float64)
    z = np.asarray(target_mm, dtype=np.float64) - eye
    norm = np.linalg.norm(z)
    if norm == 0:
        raise ValueError("look_at: eye and target coincide")
    z /= norm
    up_v = np.asarray(up, dtype=np.float64)
    if abs(np.dot(up_v, z)) > 0.999 * np.linalg.norm(up_v):
        up_v = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(-up_v, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.column_stack([x, y, z]), eye)


def rotation_angle_between(Ta: Pose, Tb: Pose) -> float:
    """Angle (rad) of the relative rotation between two poses."""
    R = Ta[:3, :3].T @ Tb[:3, :3]
    return float(np.linalg.norm(_rotation().from_matrix(R).as_rotvec()))


def incidence_cos(points: ArrayLike, normals: ArrayLike, eye: ArrayLike) -> NDArray[np.float64]:
    """|cos| of the angle between each point's unit normal and its line of sight from ``eye`` (same frame)."""
    sight = np.asarray(points, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    return np.abs(np.einsum("ij,ij->i", sight, np.asarray(normals))) / np.linalg.norm(sight, axis=1)


def points_within(points: NDArray[np.float64], centre: ArrayLike, radius_mm: float) -> NDArray[np.int64]:
    """Indices (ascending) of the (N, 3) ``points`` within ``radius_mm`` of ``centre`` (squared distances, as
    a KD-tree's ball query compares them). A slab in x, its box (a micrometre larger, so rounding cannot drop
    a point), then the distance: for a few balls in millions of points, far cheaper than building a tree."""
    c = np.asarray(centre, dtype=np.float64)
    near = np.flatnonzero(np.abs(points[:, 0] - c[0]) <= radius_mm + 1e-6)
    near = near[np.all(np.abs(points[near] - c) <= radius_mm + 1e-6, axis=1)]
    gap = points[near] - c
    return near[np.einsum("ij,ij->i", gap, gap) <= radius_mm**2]


def bounding_box(points: NDArray[np.floating[Any]]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The (lo, hi) corners (3,) of an (N, 3) point array's box, N > 0: the same values as ``points.min(0)``
    and ``points.max(0)``, taken column by column, which numpy reduces ~14 times faster than over axis 0 of
    an (N, 3) array (0.007 s against 0.1 s for 2M points)."""
    p = np.asarray(points)
    lo = np.array([p[:, j].min() for j in range(p.shape[1])], dtype=np.float64)
    hi = np.array([p[:, j].max() for j in range(p.shape[1])], dtype=np.float64)
    return lo, hi
