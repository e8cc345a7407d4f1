"""UR5e kinematics: forward kinematics, closed-form inverse kinematics (all 8 branches) and reachability.

Convention: the standard (distal) Denavit-Hartenberg parameters Universal Robots publishes, link transform
``A_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``. Base frame {B} is UR's base frame (z up along joint 1), the
tool frame {T} is the flange (z out of the flange face). With all joints at 0 the flange sits at
``(a2 + a3, -(d4 + d6), d1 - d5) = (-817.2, -232.9, 62.8)`` mm. Units: mm and rad.

The inverse kinematics is the closed form of Hawkins, "Analytic Inverse Kinematics for the Universal Robots
UR-5/UR-10 Arms" (2013), written here by hand and vectorised over many poses: no well-kept Python library
offers UR analytic IK fitting this use (ikfast bindings need generated C++, ur_ikfast/ur_kinematics are
unmaintained ROS packages, numeric solvers return one branch). Every analytic solution is polished by two
Gauss-Newton steps (near the elbow/wrist singularities ``acos`` loses precision) and then verified by FK.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cell.errors import PlanningError

Array = NDArray[np.float64]

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class DHParams:
    """Standard DH parameters of a 6R UR arm (mm, rad)."""

    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]


UR5E_DH = DHParams(
    d=(162.5, 0.0, 0.0, 133.3, 99.7, 99.6),
    a=(0.0, -425.0, -392.2, 0.0, 0.0, 0.0),
    alpha=(np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0),
)


@dataclass(frozen=True)
class IKSolutions:
    """All verified IK solutions of one pose, or why there are none.

    ``joints`` is (K, 6) rad, each angle wrapped to (-pi, pi]; ``reason`` is None when K > 0. ``singular`` is
    True when the pose lies within the singularity margin of the wrist (q5 ~ 0, q6 then arbitrary).
    """

    joints: Array
    reason: str | None
    singular: bool = False

    @property
    def ok(self) -> bool:
        return self.reason is None


def _dh(theta: Array, d: float, a: float, alpha: float) -> Array:
    """Batched DH link transform A(theta): (...,) angles -> (..., 4, 4)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    T = np.zeros(theta.shape + (4, 4))
    T[..., 0, 0] = ct
    T[..., 0, 1] = -st * ca
    T[..., 0, 2] = st * sa
    T[..., 0, 3] = a * ct
    T[..., 1, 0] = st
    T[..., 1, 1] = ct * ca
    T[..., 1, 2] = -ct * sa
    T[..., 1, 3] = a * st
    T[..., 2, 1] = sa
    T[..., 2, 2] = ca
    T[..., 2, 3] = d
    T[..., 3, 3] = 1.0
    return T


def _inv(T: Array) -> Array:
    """Batched inverse of rigid transforms (..., 4, 4)."""
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _rot_error(Ra: Array, Rb: Array) -> Array:
    """Rotation angle (rad) of Ra^T Rb, batched; accurate for tiny angles (uses the skew part)."""
    R = np.einsum("...ji,...jk->...ik", Ra, Rb)
    skew = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    s = 0.5 * np.linalg.norm(skew, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def _jacobian_of_frames(F: Array) -> Array:
    """Geometric Jacobian in {B} (..., 6, 6) from the link frames (..., 7, 4, 4) of :meth:`fk_frames`."""
    z = F[..., :6, :3, 2]
    o = F[..., :6, :3, 3]
    p = F[..., 6:7, :3, 3]
    Jv = np.cross(z, p - o)
    return np.concatenate([np.swapaxes(Jv, -1, -2), np.swapaxes(z, -1, -2)], axis=-2)


def wrap_angle(q: ArrayLike) -> Array:
    """Wrap angles (rad) to (-pi, pi]."""
    q = np.asarray(q, dtype=np.float64)
    return -np.remainder(-q + np.pi, TWO_PI) + np.pi


@dataclass(frozen=True)
class URKinematics:
    """Forward/inverse kinematics and reachability of a UR arm (default: UR5e, limits +-2 pi on every joint).

    ``singularity_margin_rad``: poses with |sin q5| below sin(margin) count as wrist-singular for
    :meth:`reachable` (the arm can be there, but joint speeds blow up nearby and q6 is undetermined).
    """

    dh: DHParams = UR5E_DH
    joint_min_rad: tuple[float, ...] = (-TWO_PI,) * 6
    joint_max_rad: tuple[float, ...] = (TWO_PI,) * 6
    singularity_margin_rad: float = np.deg2rad(2.0)
    pos_tol_mm: float = 1e-6
    rot_tol_rad: float = 1e-9
    _lo: Array = field(init=False, repr=False, compare=False)
    _hi: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_lo", np.asarray(self.joint_min_rad, dtype=np.float64))
        object.__setattr__(self, "_hi", np.asarray(self.joint_max_rad, dtype=np.float64))

    # ------------------------------------------------------------------------------------------ forward
    def fk_frames(self, q: ArrayLike) -> Array:
        """Frames of every link in {B}: (..., 7, 4, 4), index 0 = base, 6 = flange."""
        q = np.asarray(q, dtype=np.float64)
        frames = np.empty(q.shape[:-1] + (7, 4, 4))
        T = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
        frames[..., 0, :, :] = T
        for i in range(6):
            T = T @ _dh(q[..., i], self.dh.d[i], self.dh.a[i], self.dh.alpha[i])
            frames[..., i + 1, :, :] = T
        return frames

    def fk(self, q: ArrayLike) -> Array:
        """Flange pose ``T_B_T`` (4x4, mm) of joints ``q`` (rad); vectorised: (..., 6) -> (..., 4, 4)."""
        q = np.asarray(q, dtype=np.float64)
        T = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
        for i in range(6):
            T = T @ _dh(q[..., i], self.dh.d[i], self.dh.a[i], self.dh.alpha[i])
        return T

    def jacobian(self, q: ArrayLike) -> Array:
        """Geometric Jacobian in {B} (..., 6, 6): rows [v (mm/rad); w], columns joints."""
        return _jacobian_of_frames(self.fk_frames(q))

    # ------------------------------------------------------------------------------------------ inverse
    def ik_all(
        self, T_B_T: ArrayLike, q6_default: float = 0.0
    ) -> tuple[Array, NDArray[np.bool_], NDArray[np.bool_]]:
        """All 8 analytic branches for each of (N, 4, 4) poses (a single 4x4 works too).

        Returns ``(q, valid, singular)``: q (N, 8, 6) rad wrapped to (-pi, pi], NaN where the branch does not
        exist; valid (N, 8) where the FK of q matches the pose within tolerance; singular (N, 8) where
        |sin q5| < sin(singularity margin). At an exact wrist singularity q6 is set to ``q6_default``.
        Joint limits are not applied here (see :meth:`ik`).
        """
        T06 = np.asarray(T_B_T, dtype=np.float64)
        single = T06.ndim == 2
        T06 = T06.reshape(-1, 4, 4)
        q, sing8, _ = self._branches(T06, q6_default)
        Tq = self.fk(np.nan_to_num(q))
        pos_err = np.linalg.norm(Tq[..., :3, 3] - T06[:, None, :3, 3], axis=-1)
        rot_err = _rot_error(Tq[..., :3, :3], T06[:, None, :3, :3])
        valid = np.all(np.isfinite(q), -1) & (pos_err <= self.pos_tol_mm) & (rot_err <= self.rot_tol_rad)
        if single:
            return q[0], valid[0], sing8[0]
        return q, valid, sing8

    def _branches(self, T06: Array, q6_default: float) -> tuple[Array, NDArray[np.bool_], Array]:
        """Closed form for (n, 4, 4) poses: q (n, 8, 6), singular (n, 8), shoulder-wrist mm (n, 8)."""
        n = T06.shape[0]
        d1, _, _, d4, d5, d6 = self.dh.d
        a2, a3 = self.dh.a[1], self.dh.a[2]
        q = np.full((n, 8, 6), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            # q1: the wrist centre P05 must lie outside the cylinder of radius d4 around joint 1.
            p05 = T06[:, :3, 3] - d6 * T06[:, :3, 2]
            r05 = np.hypot(p05[:, 0], p05[:, 1])
            phi = np.arccos(d4 / r05)  # NaN inside the cylinder
            psi = np.arctan2(p05[:, 1], p05[:, 0])
            q1 = np.stack([psi + phi, psi - phi], -1) + np.pi / 2  # (n, 2)
            # q5 from the flange position seen along the rotated joint-1 frame.
            p = T06[:, None, :3, 3]
            s1, c1 = np.sin(q1), np.cos(q1)
            c5 = np.clip((p[..., 0] * s1 - p[..., 1] * c1 - d4) / d6, -1.0, 1.0)
            c5 = np.where(np.abs((p[..., 0] * s1 - p[..., 1] * c1 - d4) / d6) > 1.0 + 1e-9, np.nan, c5)
            a5 = np.arccos(c5)
            q5 = np.stack([a5, -a5], -1)  # (n, 2, 2)
            q1b = np.repeat(q1[:, :, None], 2, axis=2)
            s1b, c1b = np.sin(q1b), np.cos(q1b)
            s5 = np.sin(q5)
            R = T06[:, None, None, :3, :3]
            # X60, Y60 = rows 0, 1 of R06 (axes of {B} seen in {T}).
            num = -R[..., 0, 1] * s1b + R[..., 1, 1] * c1b
            den = R[..., 0, 0] * s1b - R[..., 1, 0] * c1b
            singular = np.abs(s5) < np.sin(self.singularity_margin_rad)
            exact = np.abs(s5) < 1e-12
            q6 = np.where(exact, q6_default, np.arctan2(num / s5, den / s5))
            # Planar 3R problem in joints 2-4: T14 = A1^-1 T06 A6^-1 A5^-1.
            A1 = _dh(q1b, d1, 0.0, self.dh.alpha[0])
            A5 = _dh(q5, d5, 0.0, self.dh.alpha[4])
            A6 = _dh(q6, d6, 0.0, self.dh.alpha[5])
            T14 = _inv(A1) @ T06[:, None, None] @ _inv(A6) @ _inv(A5)
            px, pz = T14[..., 0, 3], T14[..., 1, 3]
            r2 = px * px + pz * pz
            c3 = (r2 - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
            c3 = np.where(np.abs(c3) > 1.0 + 1e-9, np.nan, np.clip(c3, -1.0, 1.0))
            a3c = np.arccos(c3)
            for k3, sign in enumerate((1.0, -1.0)):
                q3 = sign * a3c
                q2 = np.arctan2(-pz, -px) - np.arcsin(-a3 * np.sin(q3) / np.sqrt(r2))
                A2 = _dh(q2, 0.0, a2, 0.0)
                A3 = _dh(q3, 0.0, a3, 0.0)
                T34 = _inv(A2 @ A3) @ T14
                q4 = np.arctan2(T34[..., 1, 0], T34[..., 0, 0])
                sol = np.stack([q1b, q2, q3, q4, q5, q6], -1)  # (n, 2, 2, 6)
                q[:, k3::2] = sol.reshape(n, 4, 6)
            sing8 = np.repeat(singular.reshape(n, 4), 2, axis=1)
            # Polish: two Gauss-Newton steps recover the precision acos loses near singular configurations.
            finite = np.all(np.isfinite(q), axis=-1)
            if finite.any():
                qf = q[finite]
                Tt = np.broadcast_to(T06[:, None], (n, 8, 4, 4))[finite]
                for _ in range(2):
                    qf = qf + self._newton_step(qf, Tt)
                q[finite] = wrap_angle(qf)
        elbow = np.repeat(np.sqrt(r2).reshape(n, 4), 2, axis=1)
        return q, sing8, elbow

    def _newton_step(self, q: Array, T_target: Array) -> Array:
        """One damped Gauss-Newton step toward ``T_target`` (batched)."""
        F = self.fk_frames(q)  # the flange pose and the Jacobian from one pass down the arm
        Tq = F[:, 6]
        dp = T_target[:, :3, 3] - Tq[:, :3, 3]
        Rerr = T_target[:, :3, :3] @ np.swapaxes(Tq[:, :3, :3], -1, -2)
        dw = 0.5 * np.stack(
            [Rerr[:, 2, 1] - Rerr[:, 1, 2], Rerr[:, 0, 2] - Rerr[:, 2, 0], Rerr[:, 1, 0] - Rerr[:, 0, 1]], -1
        )
        J = _jacobian_of_frames(F)
        err = np.concatenate([dp, dw], -1)
        return np.einsum("nij,nj->ni", np.linalg.pinv(J, rcond=1e-10), err)

    def shift_into_limits(self, q: Array, q_ref: Array | None) -> tuple[Array, NDArray[np.bool_]]:
        """Shift each wrapped angle by a multiple of 2 pi to lie within the limits, closest to ``q_ref``.

        Returns (shifted q, ok) where ok is False for solutions with a joint no shift brings inside.
        """
        ref = np.zeros(6) if q_ref is None else np.asarray(q_ref, dtype=np.float64)
        k = np.round((ref - q) / TWO_PI)
        cand = q[..., None] + TWO_PI * (k[..., None] + np.array([-1.0, 0.0, 1.0]))  # (..., 6, 3)
        inside = (cand >= self._lo[:, None] - 1e-12) & (cand <= self._hi[:, None] + 1e-12)
        dist = np.where(inside, np.abs(cand - ref[..., None]), np.inf)
        best = np.argmin(dist, axis=-1)
        shifted = np.take_along_axis(cand, best[..., None], -1)[..., 0]
        ok = np.all(np.isfinite(np.take_along_axis(dist, best[..., None], -1)[..., 0]), -1)
        return shifted, ok

    def ik(
        self, T_B_T: ArrayLike, q_ref: ArrayLike | None = None, *, allow_singular: bool = True
    ) -> IKSolutions:
        """All verified solutions of one pose within the joint limits (each joint shifted toward ``q_ref``).

        ``reason`` says why there are none: out of reach, too close to the base axis, wrist singular,
        joint limits.
        """
        T = np.asarray(T_B_T, dtype=np.float64)
        check_pose(T)
        q6_default = 0.0 if q_ref is None else float(np.asarray(q_ref)[5])
        return self._solutions(T, *self.ik_all(T, q6_default), q_ref, allow_singular)

    def _solutions(
        self,
        T: Array,
        q: Array,
        valid: NDArray[np.bool_],
        singular: NDArray[np.bool_],
        q_ref: ArrayLike | None,
        allow_singular: bool,
    ) -> IKSolutions:
        """:meth:`ik` of one pose ``T`` from its 8 branches ``(q, valid, singular)`` of :meth:`ik_all`."""
        if not valid.any():
            return IKSolutions(np.zeros((0, 6)), self.why_unreachable(T))
        shifted, in_lim = self.shift_into_limits(
            q[valid], None if q_ref is None else np.asarray(q_ref, float)
        )
        if not in_lim.any():
            return IKSolutions(
                np.zeros((0, 6)),
                "joint limits: every IK solution has a joint outside "
                f"[{np.round(self._lo, 3).tolist()}, {np.round(self._hi, 3).tolist()}] rad",
            )
        sing = singular[valid][in_lim]
        shifted = shifted[in_lim]
        if not allow_singular:
            if np.all(sing):
                margin = np.rad2deg(self.singularity_margin_rad)
                return IKSolutions(
                    np.zeros((0, 6)),
                    f"wrist singular: q5 within {margin:.1f} deg of 0 or 180 "
                    "on every branch within the joint limits",
                    True,
                )
            shifted, sing = shifted[~sing], sing[~sing]
        return IKSolutions(shifted, None, bool(np.all(sing)))

    def ik_nearest(self, T_B_T: ArrayLike, q_ref: ArrayLike, *, allow_singular: bool = True) -> Array:
        """The IK solution closest to ``q_ref`` (rad, Euclidean in joint space); PlanningError if none."""
        q_ref = np.asarray(q_ref, dtype=np.float64)
        sols = self.ik(T_B_T, q_ref, allow_singular=allow_singular)
        if not sols.ok:
            raise PlanningError(f"pose unreachable: {sols.reason}")
        return sols.joints[np.argmin(np.linalg.norm(sols.joints - q_ref, axis=1))]

    def ik_follow(self, T_B_T: ArrayLike, q_start: ArrayLike) -> Array:
        """Joints (N, 6) rad along a path of (N, 4, 4) flange poses: each pose's solution nearest to the one
        before it (the first to ``q_start``), exactly what :meth:`ik_nearest` called pose by pose returns,
        with its PlanningError at the first pose that has none.

        Why: a planned line is checked at ~60 samples, and the closed form of one pose costs about as much
        as that of 60 (numpy's per-call overhead), so the branches of every sample are solved in one batch;
        only the choice of branch, which depends on the previous sample's, goes pose by pose. A sample near
        the wrist singularity, where ``q6`` depends on the previous joints, or one without a solution within
        the limits, is solved alone by :meth:`ik_nearest` (the same arithmetic, the same error).
        """
        poses = np.asarray(T_B_T, dtype=np.float64).reshape(-1, 4, 4)
        q = np.asarray(q_start, dtype=np.float64)
        out = np.empty((len(poses), 6))
        finite = np.all(np.isfinite(poses), axis=(1, 2))
        q_all, valid, singular = self.ik_all(np.where(finite[:, None, None], poses, np.eye(4)))
        rigid = _rigid(poses)
        for i, T in enumerate(poses):
            if not rigid[i]:
                check_pose(T)  # its error, at the first such pose (as ik_nearest pose by pose)
            if valid[i].any() and not singular[i].any():
                shifted, in_lim = self.shift_into_limits(q_all[i][valid[i]], q)
                if in_lim.any():
                    sols = shifted[in_lim]
                    q = out[i] = sols[np.argmin(np.linalg.norm(sols - q, axis=1))]
                    continue
            q = out[i] = self.ik_nearest(T, q)
        return out

    def reachable(self, T_B_T: ArrayLike, q_ref: ArrayLike | None = None) -> tuple[bool, str]:
        """Can the arm stand at ``T_B_T`` away from the wrist singularity? Returns (ok, reason or 'ok')."""
        sols = self.ik(T_B_T, q_ref, allow_singular=False)
        return (True, "ok") if sols.ok else (False, sols.reason or "")

    def reachable_each(self, T_B_T: ArrayLike) -> list[tuple[bool, str]]:
        """:meth:`reachable` of each of (N, 4, 4) poses, the same answers and reasons, the closed form of all
        of them in one batch (a viewpoint's rolls are checked together: numpy's per-call overhead, not the
        arithmetic, is what one pose costs)."""
        poses = np.asarray(T_B_T, dtype=np.float64).reshape(-1, 4, 4)
        for T in poses[~_rigid(poses)]:
            check_pose(T)  # its error
        q, valid, singular = self.ik_all(poses)
        out = []
        for i, T in enumerate(poses):
            sols = self._solutions(T, q[i], valid[i], singular[i], None, False)
            out.append((True, "ok") if sols.ok else (False, sols.reason or ""))
        return out

    def reachable_many(self, T_B_T: ArrayLike) -> Array:
        """Vectorised reachability of (N, 4, 4) poses (limits +-2 pi style: any wrapped angle fits)."""
        q, valid, singular = self.ik_all(np.asarray(T_B_T, dtype=np.float64).reshape(-1, 4, 4))
        _, in_lim = self.shift_into_limits(np.nan_to_num(q), None)
        return np.any(valid & ~singular & in_lim, axis=-1)

    def why_unreachable(self, T: Array) -> str:
        """Say why no branch exists, from the geometry of the closed form."""
        d4, d6 = self.dh.d[3], self.dh.d[5]
        p05 = T[:3, 3] - d6 * T[:3, 2]
        r05 = float(np.hypot(p05[0], p05[1]))
        if r05 < d4:
            return (
                f"too close to the base axis: wrist centre {r05:.1f} mm from the joint 1 axis, "
                f"needs >= {d4:.1f} mm"
            )
        _, _, elbow = self._branches(T[None], 0.0)
        elbow = elbow[np.isfinite(elbow)]
        if elbow.size == 0:
            return "out of reach: no wrist angle q5 joins this flange orientation to its position"
        reach = abs(self.dh.a[1]) + abs(self.dh.a[2])
        inner = abs(abs(self.dh.a[1]) - abs(self.dh.a[2]))
        if np.all(elbow > reach):
            return (
                f"out of reach: shoulder-to-wrist distance {elbow.min():.1f} mm exceeds the arm's "
                f"{reach:.1f} mm"
            )
        if np.all(elbow < inner):
            return (
                f"too close to the shoulder: shoulder-to-wrist distance {elbow.max():.1f} mm < {inner:.1f} mm"
            )
        return "out of reach: no arm configuration attains this position and orientation"


def _rigid(T: Array) -> NDArray[np.bool_]:
    """Which of (N, 4, 4) matrices :func:`check_pose` accepts (its tests, batched)."""
    finite = np.all(np.isfinite(T), axis=(1, 2))
    R = np.where(finite[:, None, None], T, 0.0)[:, :3, :3]
    return (
        finite
        & np.all(np.isclose(np.swapaxes(R, 1, 2) @ R, np.eye(3), atol=1e-6), axis=(1, 2))
        & (np.linalg.det(R) >= 0)
        & np.all(np.isclose(T[:, 3], [0.0, 0.0, 0.0, 1.0]), axis=1)
    )


def check_pose(T: Array) -> None:
    """PlanningError unless T is a 4x4 rigid transform."""
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise PlanningError(f"pose must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (
        not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        or np.linalg.det(R) < 0
        or not np.allclose(T[3], [0, 0, 0, 1])
    ):
        raise PlanningError(
            "pose is not a rigid transform (rotation not orthonormal or bottom row not 0 0 0 1)"
        )


UR5E = URKinematics()
"""The default UR5e model: standard DH, limits +-2 pi."""


# ---------------------------------------------------------------------------------------------- timing
def trapezoid_duration(distance: float, speed: float, accel: float) -> float:
    """Time (s) of a rest-to-rest move of ``distance`` with a trapezoidal speed profile.

    Cruise at ``speed`` when the distance allows (d >= v^2/a: t = d/v + v/a); otherwise a triangular
    profile peaking at sqrt(d a): t = 2 sqrt(d/a). Units are any consistent pair (mm, mm/s, mm/s^2 or rad...).
    """
    return float(trapezoid_time_at(distance, distance, speed, accel))


def trapezoid_time_at(s: ArrayLike, distance: float, speed: float, accel: float) -> Array:
    """Time (s) at which the trapezoidal move of ``distance`` has covered ``s`` (vectorised over s)."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, distance)
    if distance <= 0.0:
        return np.zeros_like(s)
    vp = min(speed, float(np.sqrt(distance * accel)))  # peak speed: cruise or triangular apex
    ta, sa = vp / accel, vp * vp / (2.0 * accel)
    total = distance / vp + vp / accel
    return np.where(
        s < sa,
        np.sqrt(2.0 * s / accel),
        np.where(
            s <= distance - sa,
            ta + (s - sa) / vp,
            total - np.sqrt(np.maximum(2.0 * (distance - s) / accel, 0.0)),
        ),
    )
