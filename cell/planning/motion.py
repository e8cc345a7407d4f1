"""Collision-checked motion between viewpoints.

A straight line or a joint-space move between two clear sensor poses can still sweep the 430 mm sensor bar
or the arm's own links (capsules, cell.planning.arm_body) through the part or the table (a wrist that
flips, a tilted view close to the table, an elbow swinging over a tall part). Before the cell
moves, it simulates the candidate paths against the nominal CAD and the table with the robot's own kinematics
and takes
the first that stays clear:

1. a straight line to the target;
2. retract, traverse, approach: straight up to a common safe height, across at that height while turning to
   the target orientation, straight down onto the target;
3. a joint move to the target lifted to the safe height, then straight down;
4. a joint move to the target;
5. options 3 and 4 from the home configuration, after a joint move home.

A line that passes close to a singularity is run slower, so that no joint exceeds its speed limit.

Heights are along the base frame's z axis, vertical in every cell we build (the base stands upright).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from cell.errors import PlanningError
from cell.geometry import Pose
from cell.planning.kinematics import URKinematics
from cell.planning.reach import ReachChecker

STEP_MM = 5.0  # path samples for the clearance check
STEP_RAD = np.deg2rad(2.0)
MIN_SPEED_SCALE = 0.1


@dataclass(frozen=True)
class Move:
    """One robot command: a linear move to a flange pose T_B_T or a joint move to joint angles."""

    kind: Literal["linear", "joint"]
    target: NDArray[np.float64]  # (4, 4) T_B_T for linear, (6,) rad for joint
    speed_scale: float = 1.0  # a line close to a singularity runs slower so no joint exceeds its limit


def linear_samples(T_a: Pose, T_b: Pose) -> NDArray[np.float64]:
    """Flange poses along a straight line with slerped orientation, one every STEP_MM / STEP_RAD."""
    rot = Rotation.from_matrix(np.stack([T_a[:3, :3], T_b[:3, :3]]))
    angle = float(np.linalg.norm((rot[0].inv() * rot[1]).as_rotvec()))
    n = int(max(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]) / STEP_MM, angle / STEP_RAD, 1)) + 1
    s = np.linspace(0.0, 1.0, n)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Slerp([0.0, 1.0], rot)(s).as_matrix()
    out[:, :3, 3] = T_a[:3, 3] + s[:, None] * (T_b[:3, 3] - T_a[:3, 3])
    return out


class MotionPlanner:
    """Chooses a clear path between flange poses for one cell and one part."""

    def __init__(
        self,
        reach: ReachChecker,
        kinematics: URKinematics,
        lift_mm: float,
        z_max_mm: float,
        tcp_speed_mm_s: float,
        joint_speed_limit_rad_s: float = np.pi,
    ) -> None:
        self.reach = reach
        self.kin = kinematics
        self.lift_mm = lift_mm
        self.z_max_mm = z_max_mm
        self.tcp_speed_mm_s = tcp_speed_mm_s  # the speed lines are run at
        self.joint_speed_limit = joint_speed_limit_rad_s  # near a singularity a line needs more: refuse it

    def _lifted(self, T: Pose, z: float) -> Pose:
        out = T.copy()
        out[2, 3] = max(z, T[2, 3])
        return out

    def _line(self, T_a: Pose, T_b: Pose, q_a: NDArray[np.float64]) -> tuple[Move | None, str, NDArray]:
        """The linear move if it is clear and continuously solvable, slowed down where a joint would exceed
        its speed limit (down to MIN_SPEED_SCALE: slower than that means a singularity or a branch flip);
        also the joints at its end."""
        samples = linear_samples(T_a, T_b)
        ok, why = self.reach.path_clear(samples)
        if not ok:
            return None, why, q_a
        try:  # each sample's solution nearest to the previous one's (ik_nearest in turn, batched)
            path = np.concatenate([q_a[None], self.kin.ik_follow(samples[1:], q_a)])
        except PlanningError as exc:
            return None, str(exc), q_a
        # each sample's duration as the robot times it: translation at the TCP speed, rotation at the joint
        # speed limit, whichever takes longer (a pure reorientation is not a singularity)
        turns = np.linalg.norm(
            Rotation.from_matrix(np.swapaxes(samples[:-1, :3, :3], 1, 2) @ samples[1:, :3, :3]).as_rotvec(),
            axis=1,
        )
        dt = np.maximum(
            np.maximum(
                np.linalg.norm(samples[1:, :3, 3] - samples[:-1, :3, 3], axis=1) / self.tcp_speed_mm_s,
                turns / self.joint_speed_limit,
            ),
            1e-6,
        )
        worst = float(np.max(np.abs(np.diff(path, axis=0)).max(axis=1) / dt, initial=0.0))
        q = path[-1]
        ok, why = self.reach.arm_clear(path)
        if not ok:
            return None, why, q_a
        scale = min(1.0, 0.9 * self.joint_speed_limit / worst) if worst > 0 else 1.0
        if scale < MIN_SPEED_SCALE:
            return None, f"the line passes a singularity (a joint would need {worst:.1f} rad/s)", q_a
        return Move("linear", T_b, scale), "clear", q

    def _joint_ok(self, q_a: NDArray[np.float64], q_b: NDArray[np.float64]) -> tuple[bool, str]:
        n = int(np.abs(q_b - q_a).max() / STEP_RAD) + 2
        qs = q_a + np.linspace(0.0, 1.0, n)[:, None] * (q_b - q_a)
        ok, why = self.reach.path_clear(self.kin.fk(qs))
        return self.reach.arm_clear(qs) if ok else (ok, why)

    def plan(
        self, T_from: Pose, q_from: NDArray[np.float64], T_to: Pose, q_home: NDArray[np.float64] | None = None
    ) -> tuple[list[Move], list[str]]:
        """Moves from the current flange pose (and joints) to ``T_to``, and why earlier options were dropped.
        Raises PlanningError naming every option's reason when none is clear."""
        rejected: list[str] = []
        move, why, _ = self._line(T_from, T_to, q_from)
        if move is not None:
            return [move], rejected
        rejected.append(f"straight line: {why}")
        z_safe = min(max(T_from[2, 3], T_to[2, 3]) + self.lift_mm, self.z_max_mm)
        up, across = self._lifted(T_from, z_safe), self._lifted(T_to, z_safe)
        q = q_from
        moves: list[Move] = []
        for a, b in ((T_from, up), (up, across), (across, T_to)):
            move, why, q = self._line(a, b, q)
            if move is None:
                rejected.append(f"retract-traverse-approach: {why}")
                break
            if not np.allclose(a, b):
                moves.append(move)
        else:
            return moves, rejected
        starts = [("", q_from)] + ([("via home, ", q_home)] if q_home is not None else [])
        for label, q_start in starts:
            prefix = [Move("joint", q_start)] if label else []
            if label:
                ok, why = self._joint_ok(q_from, q_start)
                if not ok:
                    rejected.append(f"joint move home: {why}")
                    continue
            for name, T_joint, then_down in (
                ("above the target, then down", across, True),
                ("to the target", T_to, False),
            ):
                try:
                    branches = self._branches(T_joint, q_start)
                except PlanningError as exc:
                    rejected.append(f"{label}joint move {name}: {exc}")
                    continue
                why = ""
                for q_goal in branches:
                    ok, why = self._joint_ok(q_start, q_goal)
                    down = None
                    if ok and then_down:
                        down, why, _ = self._line(across, T_to, q_goal)
                        ok = down is not None
                    if ok:
                        return prefix + [Move("joint", q_goal)] + ([down] if down else []), rejected
                rejected.append(f"{label}joint move {name}: {why}")
        raise PlanningError("no collision-free path to the view: " + "; ".join(rejected))

    def _branches(self, T: Pose, q_ref: NDArray[np.float64]) -> list[NDArray[np.float64]]:
        """Every IK branch of ``T`` (shoulder, elbow, wrist), nearest to ``q_ref`` first: a joint move on the
        nearest branch can dip the flange below the envelope or sweep the arm through the part where another
        branch stays clear. PlanningError when there is none."""
        sols = self.kin.ik(T, q_ref)
        if not sols.ok:
            raise PlanningError(f"pose unreachable: {sols.reason}")
        order = np.argsort(np.abs(sols.joints - q_ref).max(axis=1))
        return [sols.joints[i] for i in order]
