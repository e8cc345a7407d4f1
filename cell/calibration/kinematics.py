"""Robot kinematic calibration: the arm's link lengths and joint zeros from board views, with the hand-eye.

A UR arm reports its flange pose from its nominal kinematics. Its real links differ by a few tenths of a
millimetre and its joint zeros by a few hundredths of a degree, so a reported pose is off in a pose-dependent
way that no hand-eye can absorb (docs/calibration.md: the hand-eye sweep and the pillar's end views). With a
ChArUco board lying still, each view gives the joint angles ``q_k`` and the board's corners in the image; the
model

    T_C_Bd(k) = inv(T_T_C) @ inv(FK(q_k + dq; d + dd, a + da)) @ T_B_Bd

predicts those corners through the calibrated camera (cv2.projectPoints). The link-length errors ``dd``,
``da`` (of the non-zero standard DH lengths), the joint zeros ``dq``, the hand-eye ``T_T_C`` and the board's
pose in the base ``T_B_Bd`` are found together by least squares on the corners' reprojection error (scipy
least_squares), with a prior on the kinematic errors (``sigma_link_mm``, ``sigma_zero_deg``: what the arm's
maker tolerates) that keeps the combinations the views cannot separate (e.g. d6 against the hand-eye's z) at
zero. A constant offset of every flange pose is the board's pose to the fit, harmless (the part's datums take
it); what the calibration removes is the pose-dependent rest, which moves views against each other.

What it leaves is known too: the fit's posterior covariance (corner noise and the prior), carried through the
chain to the camera, says how far apart two views' poses may still be (:func:`camera_pose_spread`).
That is the multi-view refinement's prior for a calibrated cell: a cell that knows its views to 0.1 mm must
not let noise slide them by the millimetre an uncalibrated arm may be off.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cell.errors import CalibrationError
from cell.geometry import Pose, invert, pose_from_xyz_rotvec, pose_to_xyz_rotvec
from cell.planning.kinematics import UR5E, DHParams, URKinematics

Array = NDArray[np.float64]


@dataclass(frozen=True)
class KinematicErrors:
    """Corrections of the nominal arm: ``dd``, ``da`` (6 each, mm) added to the standard DH d and a, ``dq``
    (6, rad) added to the reported joint angles."""

    dd: Array
    da: Array
    dq: Array

    @classmethod
    def zero(cls) -> KinematicErrors:
        return cls(np.zeros(6), np.zeros(6), np.zeros(6))

    def model(self, nominal: URKinematics = UR5E) -> URKinematics:
        """The calibrated arm (its joint zeros are applied by :meth:`flange`)."""
        dh = nominal.dh
        return URKinematics(
            dh=DHParams(
                d=tuple((np.asarray(dh.d) + self.dd).tolist()),
                a=tuple((np.asarray(dh.a) + self.da).tolist()),
                alpha=dh.alpha,
            )
        )

    def flange(self, joints_rad: NDArray, nominal: URKinematics = UR5E) -> Array:
        """``T_B_T`` of the calibrated arm at the reported joint angles (rad)."""
        return self.model(nominal).fk(np.asarray(joints_rad, dtype=np.float64) + self.dq)


@dataclass(frozen=True)
class BoardObservation:
    """One view: reported joints (rad), the board's detected corners (px), their board coordinates (mm)."""

    joints_rad: Array
    corners_px: Array
    object_mm: Array


@dataclass
class KinematicCalibration:
    """The fit: the arm's errors, the hand-eye ``T_T_C`` and board pose ``T_B_Bd`` found with them, the rms
    reprojection error (px) with them and with the nominal arm (hand-eye and board refit alone), and the
    per-view rms (px)."""

    errors: KinematicErrors
    T_T_C: Pose
    T_B_Bd: Pose
    rms_px: float
    rms_px_nominal_arm: float
    per_view_px: list[float]
    x: Array  # the fitted parameters, in :func:`_unpack`'s order
    covariance: Array  # their posterior covariance (wider when the corners are noisier than assumed)


def camera_pose_spread(
    x: Array,
    covariance: Array,
    joints: Sequence[Array],
    standoff_mm: float,
    nominal: URKinematics = UR5E,
) -> Array:
    """Per pose of ``joints`` (rad, at least 2), the 1-sigma error per axis of the camera pose that the
    calibration ``x`` (:func:`_unpack`'s order, with ``covariance``) gives there, relative to the mean over
    the poses: column 0 of the point ``standoff_mm`` in front of the camera (mm), column 1 of the camera's
    rotation (rad). A common error of all poses is left out (the part's alignment takes it). The covariance
    is carried through the chain by finite differences (one forward kinematics per pose and parameter)."""
    if len(joints) < 2:
        raise CalibrationError("robot kinematic calibration: a pose spread needs at least 2 poses")

    def cameras(p: Array) -> tuple[Array, list[Rotation]]:
        errors, T_T_C, _ = _unpack(p, nominal, True)
        model = errors.model(nominal)
        points, rotations = [], []
        for q in joints:
            T_B_C = model.fk(np.asarray(q, dtype=np.float64) + errors.dq) @ T_T_C
            points.append(T_B_C[:3, :3] @ [0.0, 0.0, standoff_mm] + T_B_C[:3, 3])
            rotations.append(Rotation.from_matrix(T_B_C[:3, :3]))
        return np.array(points), rotations

    base_points, base_rot = cameras(x)
    steps = np.sqrt(np.maximum(np.diag(covariance), 1e-18)) * 1e-2
    J = np.empty((6 * len(joints), len(x)))
    for k, h in enumerate(steps):
        p = x.copy()
        p[k] += h
        points, rot = cameras(p)
        turn = np.array([(r * b.inv()).as_rotvec() for r, b in zip(rot, base_rot, strict=True)])
        J[:, k] = np.column_stack([points - base_points, turn]).ravel() / h
    n = len(joints)
    relative = np.kron(np.eye(n) - 1.0 / n, np.eye(6)) @ J  # each pose's error minus the poses' mean
    var = np.einsum("ij,jk,ik->i", relative, covariance, relative).reshape(n, 6)
    return np.column_stack([np.sqrt(var[:, :3].mean(axis=1)), np.sqrt(var[:, 3:].mean(axis=1))])


def _free(nominal: URKinematics) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of the DH d and a that are not zero (a zero length stays zero: there is no link to err)."""
    return np.flatnonzero(np.asarray(nominal.dh.d)), np.flatnonzero(np.asarray(nominal.dh.a))


def _unpack(x: Array, nominal: URKinematics, kinematic: bool) -> tuple[KinematicErrors, Pose, Pose]:
    i_d, i_a = _free(nominal)
    dd, da, dq = np.zeros(6), np.zeros(6), np.zeros(6)
    k = 0
    if kinematic:
        dd[i_d] = x[: len(i_d)]
        k = len(i_d)
        da[i_a] = x[k : k + len(i_a)]
        k += len(i_a)
        dq = x[k : k + 6]
        k += 6
    T_T_C = pose_from_xyz_rotvec(x[k + 3 : k + 6], x[k : k + 3])
    T_B_Bd = pose_from_xyz_rotvec(x[k + 9 : k + 12], x[k + 6 : k + 9])
    return KinematicErrors(dd, da, dq), T_T_C, T_B_Bd


def _reprojection(
    x: Array,
    views: Sequence[BoardObservation],
    K: Array,
    dist: Array,
    nominal: URKinematics,
    kinematic: bool,
) -> list[Array]:
    errors, T_T_C, T_B_Bd = _unpack(x, nominal, kinematic)
    model = errors.model(nominal)
    out = []
    for v in views:
        T_C_Bd = invert(T_T_C) @ invert(model.fk(v.joints_rad + errors.dq)) @ T_B_Bd
        rvec = cv2.Rodrigues(T_C_Bd[:3, :3])[0]
        seen, _ = cv2.projectPoints(v.object_mm, rvec, T_C_Bd[:3, 3], K, dist)
        out.append(seen.reshape(-1, 2) - v.corners_px)
    return out


def fit_kinematics(
    views: Sequence[BoardObservation],
    K: Array,
    dist: Array,
    T_T_C0: Pose,
    T_C_Bd0: Pose,
    *,
    sigma_link_mm: float = 0.5,
    sigma_zero_deg: float = 0.05,
    corner_noise_px: float = 0.1,
    nominal: URKinematics = UR5E,
) -> KinematicCalibration:
    """The arm's errors, hand-eye and board pose from ``views`` (cameras intrinsics ``K``, ``dist``), started
    from the hand-eye ``T_T_C0`` and the first view's board pose ``T_C_Bd0`` (solvePnP)."""
    if len(views) < 8:
        raise CalibrationError(
            f"robot kinematic calibration: {len(views)} board views; at least 8 are needed (24 recommended)"
        )
    i_d, i_a = _free(nominal)
    T_B_Bd0 = nominal.fk(views[0].joints_rad) @ T_T_C0 @ T_C_Bd0
    poses0 = np.concatenate([_xyz_rotvec(T_T_C0), _xyz_rotvec(T_B_Bd0)])
    prior = np.concatenate(
        [np.full(len(i_d) + len(i_a), sigma_link_mm), np.full(6, np.deg2rad(sigma_zero_deg))]
    )

    def residuals(x: Array, kinematic: bool) -> Array:
        px = np.concatenate([r.ravel() for r in _reprojection(x, views, K, dist, nominal, kinematic)])
        if not kinematic:
            return px / corner_noise_px
        return np.concatenate([px / corner_noise_px, x[: len(prior)] / prior])

    hand_eye_only = least_squares(residuals, poses0, args=(False,), x_scale="jac", method="lm")
    x0 = np.concatenate([np.zeros(len(prior)), hand_eye_only.x])
    full = least_squares(residuals, x0, args=(True,), x_scale="jac", method="lm")
    errors, T_T_C, T_B_Bd = _unpack(full.x, nominal, True)
    per_view = _reprojection(full.x, views, K, dist, nominal, True)
    nominal_px = _reprojection(hand_eye_only.x, views, K, dist, nominal, False)
    # residuals are in sigmas, so inv(J^T J) is the covariance when the corners are as noisy as assumed;
    # noisier corners (chi^2 per degree of freedom above 1) widen it, quieter ones do not narrow it
    n_px = sum(r.size for r in per_view)
    chi2_dof = float(np.sum((np.concatenate([r.ravel() for r in per_view]) / corner_noise_px) ** 2))
    chi2_dof /= max(n_px - len(full.x), 1)
    J = np.asarray(full.jac)  # method="lm": a dense Jacobian
    covariance = np.linalg.pinv(J.T @ J) * max(1.0, chi2_dof)
    return KinematicCalibration(
        errors,
        T_T_C,
        T_B_Bd,
        _rms(per_view),
        _rms(nominal_px),
        [float(np.sqrt(np.mean(r**2))) for r in per_view],
        full.x,
        covariance,
    )


def _xyz_rotvec(T: Pose) -> Array:
    """(rotation vector, translation) of ``T``: the parameter order of :func:`_unpack`."""
    xyz_rv = pose_to_xyz_rotvec(T)
    return np.concatenate([xyz_rv[3:], xyz_rv[:3]])


def _rms(residuals: list[Array]) -> float:
    return float(np.sqrt(np.mean(np.concatenate([r.ravel() for r in residuals]) ** 2)))
