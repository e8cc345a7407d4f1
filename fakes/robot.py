"""Simulated UR5e behind the :class:`cell.contracts.Robot` contract.

What it checks before moving (refusal, nothing moves, PlanningError/DeviceFault naming the robot): connected,
no protective stop, speed and acceleration within the configured maxima, target a rigid transform, flange
inside the configured envelope (base frame), every sample of the path reachable by IK on a continuous branch
within the joint limits and without joint speeds above the UR5e's 180 deg/s (singularity crossings).

What happens while moving (simulated time on a :class:`~fakes.clock.SimClock`, nothing sleeps): the flange and
the tool body points must stay above the table (world z > clearance) and out of the obstacle mesh, and the
arm's links (capsules of cell.planning.arm_body, exact distance to the mesh) must not touch either; on contact
the arm stops at the last safe sample, the protective stop latches and DeviceFault says what touched what, as
a UR controller would. ``inject_fault`` makes the next move fail midway the same way. ``command_log`` keeps
every command with its target, speed, acceleration, start time, duration and outcome.

Motion is asynchronous on the sim clock, like a UR controller's async moveL/moveJ: :meth:`start_linear` /
:meth:`start_joint` start a checked path at the clock's present time, and the arm's pose is a function of the
clock from then on. :meth:`wait` advances the clock by one poll period (and sleeps as long in wall time when
``robot.options.sim_realtime_factor`` is set, or the environment's ``CELL_SIM_REALTIME_FACTOR``, which wins:
a harness knob that paces the arm without changing the cell config, so that a signal can arrive mid-move;
``CELL_SIM_MOTION_LOG`` names a file where each started move appends a JSON line, so that a harness signals
a process once its arm is in motion, not while the move is still being checked); ``move_linear`` /
``move_joint`` are start + wait. :meth:`stop` may be called from a signal handler or another thread while a
move runs: the arm decelerates from the speed it has at that instant (at the configured maximum acceleration,
like stopL/stopJ) and the move raises :class:`~cell.errors.MotionStopped`. A watchdog
(``robot.options.watchdog_hz``, default 10 Hz, like ur_rtde's ``setWatchdog``) stops the arm the same way when
nobody kicks it for one period; the polling move kicks it, so it trips when the controlling code stops
polling, as it does when the process dies.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation, Slerp

from cell.config import RobotConfig
from cell.contracts import Envelope, RobotMode, RobotState
from cell.errors import CellError, DeviceFault, DeviceTimeout, MotionStopped, PlanningError
from cell.planning.arm_body import arm_samples
from cell.planning.kinematics import (
    UR5E,
    URKinematics,
    check_pose,
    trapezoid_duration,
    trapezoid_time_at,
)
from fakes.clock import SimClock

Array = NDArray[np.float64]

UR5E_MAX_JOINT_SPEED_RAD_S = math.pi  # hardware limit of every UR5e joint (180 deg/s)
FaultKind = Literal["protective_stop", "connection_loss", "safeguard_stop"]
POLL_S = 0.004  # how often a blocking move polls the motion (ur_rtde reads its data at 500 Hz = 2 ms)


@dataclass
class _Motion:
    """A path in progress: joint samples, their path parameter (mm, or rad for joint moves and rotation-timed
    lines) and times from the start; ``end`` is the last sample the arm reaches (a contact or an injected
    fault cuts it short, ``error`` then says why). A stop sets ``stop_t`` (s from the start), the speed it
    had then and the time the deceleration ends."""

    entry: dict[str, Any]
    path: Array
    s: Array
    times: Array
    t0: float
    end: int
    error: CellError | None
    outcome: str
    a_stop: float
    stop_t: float | None = None
    stop_v: float = 0.0
    stop_end_t: float = 0.0

    def s_at(self, t: float) -> float:
        """Path parameter at ``t`` seconds from the start (trapezoid along the samples, or the deceleration
        ramp after a stop), never beyond the last reachable sample."""
        s_end = float(self.s[self.end])
        if self.stop_t is not None and t >= self.stop_t:
            dt = min(t - self.stop_t, self.stop_end_t - self.stop_t)
            s0 = float(np.interp(self.stop_t, self.times[: self.end + 1], self.s[: self.end + 1]))
            return min(s0 + self.stop_v * dt - 0.5 * self.a_stop * dt * dt, s_end)
        return float(np.interp(t, self.times[: self.end + 1], self.s[: self.end + 1]))

    def q_at(self, t: float) -> Array:
        s = self.s_at(t)
        if self.s[-1] <= 0.0:
            return self.path[-1].copy()
        k = int(np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2))
        w = 0.0 if self.s[k + 1] == self.s[k] else (s - self.s[k]) / (self.s[k + 1] - self.s[k])
        return self.path[k] + min(max(w, 0.0), 1.0) * (self.path[k + 1] - self.path[k])

    def finish_t(self) -> float:
        return self.stop_end_t if self.stop_t is not None else float(self.times[self.end])

    def begin_stop(self, t: float, error: CellError, outcome: str) -> bool:
        """Decelerate from ``t`` (s from the start) unless the motion ends before; True if it stops."""
        if self.stop_t is not None or t >= float(self.times[self.end]):
            return False
        h = 1e-4  # the speed of the sampled trapezoid (exact in the cruise, a segment's mean elsewhere)
        v = 0.0 if t <= 0.0 else (self.s_at(t + h) - self.s_at(max(t - h, 0.0))) / (t + h - max(t - h, 0.0))
        self.stop_t, self.stop_v = t, max(v, 0.0)
        self.stop_end_t = t + self.stop_v / self.a_stop
        if self.end == len(self.s) - 1 or self.s_at(self.stop_end_t) < float(self.s[self.end]):
            self.error, self.outcome = error, outcome  # otherwise the contact comes first and stays the cause
        return True


class _CollisionModel:
    """Table plane z=0 and an optional obstacle mesh in {W}, against flange + tool body points in {T}."""

    def __init__(self, obstacles_W: trimesh.Trimesh | None, tool_body_T: Array | None, clearance_mm: float):
        pts = np.zeros((1, 3)) if tool_body_T is None else np.vstack([np.zeros((1, 3)), tool_body_T])
        self.points_T = pts  # row 0 is the flange origin
        self.mesh = obstacles_W
        self.clearance = clearance_mm
        self.hull_eq: Array | None = None
        if tool_body_T is not None and len(tool_body_T) >= 4:
            try:
                self.hull_eq = ConvexHull(tool_body_T).equations  # (F, 4): inside when n.p + c <= 0
            except QhullError:  # flat or degenerate tool body: points only
                self.hull_eq = None

    def first_contact(self, T_W_T: Array) -> tuple[int, str] | None:
        """Index of the first sample pose (n, 4, 4) in contact and what touches, or None."""
        pts = np.einsum("nij,mj->nmi", T_W_T[:, :3, :3], self.points_T) + T_W_T[:, None, :3, 3]
        hits: list[tuple[int, str]] = []
        low = pts[..., 2] < self.clearance
        if low.any():
            k = int(np.argmax(low.any(axis=1)))
            m = int(np.argmax(low[k]))
            what = "flange" if m == 0 else f"tool body point {m - 1}"
            hits.append((k, f"{what} touches the table at world z = {pts[k, m, 2]:.2f} mm"))
        if self.mesh is not None:
            hit = self._mesh_contact(self.mesh, T_W_T, pts)
            if hit is not None:
                hits.append(hit)
        return min(hits) if hits else None

    def arm_contact(self, kin: URKinematics, q: Array, T_W_B: Array) -> tuple[int, str] | None:
        """Index of the first joint sample (n, 6) where a link capsule touches the table or the obstacle
        mesh (surface within the capsule radius, exact distance), and what touches, or None."""
        arm = arm_samples(kin, q)
        pts = np.einsum("ij,nmj->nmi", T_W_B[:3, :3], arm.points_B) + T_W_B[:3, 3]
        touch = pts[..., 2] < arm.radius_mm
        if self.mesh is not None:
            reach = arm.radius_mm.max()
            lo, hi = self.mesh.bounds[0] - reach, self.mesh.bounds[1] + reach
            near = np.all((pts >= lo) & (pts <= hi), axis=-1) & ~touch
            if near.any():
                sd = trimesh.proximity.signed_distance(self.mesh, pts[near])  # > 0 inside the mesh
                touch[near] = sd > -np.broadcast_to(arm.radius_mm, near.shape)[near]
        if not touch.any():
            return None
        k = int(np.argmax(touch.any(axis=1)))
        m = int(np.argmax(touch[k]))
        where = "the table" if pts[k, m, 2] < arm.radius_mm[m] else "the obstacle mesh"
        return k, f"robot {arm.link[m]} touches {where} near world {np.round(pts[k, m], 1).tolist()} mm"

    def _mesh_contact(self, mesh: trimesh.Trimesh, T_W_T: Array, pts: Array) -> tuple[int, str] | None:
        lo, hi = mesh.bounds[0] - self.clearance, mesh.bounds[1] + self.clearance
        n, m = pts.shape[:2]
        near = np.all((pts >= lo) & (pts <= hi), axis=-1)  # cheap box pre-filter before exact distances
        first: tuple[int, str] | None = None
        if near.any():
            idx = np.argwhere(near)
            sd = trimesh.proximity.signed_distance(mesh, pts[near])  # > 0 inside the mesh
            bad = sd > -self.clearance
            if bad.any():
                k, j = idx[np.argmax(bad)]
                what = "flange" if j == 0 else f"tool body point {j - 1}"
                first = (
                    int(k),
                    f"{what} hits the obstacle mesh at world {np.round(pts[k, j], 1).tolist()} mm",
                )
        if (
            self.hull_eq is not None
        ):  # obstacle vertices inside the tool body (catches parts poking between corners)
            body_lo, body_hi = pts[:, 1:].min(axis=1), pts[:, 1:].max(axis=1)
            overlap = np.all((body_hi >= lo) & (body_lo <= hi), axis=-1)
            for k in np.flatnonzero(overlap):
                if first is not None and k >= first[0]:
                    break
                v_T = (mesh.vertices - T_W_T[k, :3, 3]) @ T_W_T[k, :3, :3]
                inside = np.all(v_T @ self.hull_eq[:, :3].T + self.hull_eq[:, 3] <= 0.0, axis=1)
                if inside.any():
                    v = mesh.vertices[np.argmax(inside)]
                    first = (
                        int(k),
                        f"tool body hits the obstacle mesh near world {np.round(v, 1).tolist()} mm",
                    )
                    break
        return first


class SimRobot:
    """A simulated UR5e arm on a :class:`SimClock`; see the module docstring for what it checks."""

    def __init__(
        self,
        config: RobotConfig,
        *,
        clock: SimClock | None = None,
        obstacles_W: trimesh.Trimesh | None = None,
        tool_body_T: ArrayLike | None = None,
        clearance_mm: float = 0.0,
        kinematics: URKinematics = UR5E,
        path_step_mm: float = 2.0,
        path_step_rad: float = math.radians(0.5),
    ) -> None:
        self.config = config
        self.name = config.name
        self.clock = clock or SimClock()
        self.kin = kinematics
        self.T_W_B = config.T_W_B.matrix()
        self._envelope = Envelope(config.envelope_min_mm, config.envelope_max_mm)
        body = None if tool_body_T is None else np.asarray(tool_body_T, dtype=np.float64).reshape(-1, 3)
        self._collision = _CollisionModel(obstacles_W, body, clearance_mm)
        self._step_mm, self._step_rad = path_step_mm, path_step_rad
        self._q = np.deg2rad(np.asarray(config.home_joints_deg, dtype=np.float64))
        self._connected = False
        self._protective_stop = False
        self._fault: tuple[FaultKind, float | None] | None = None
        self._safeguard_stop = False
        self._motion: _Motion | None = None
        self._error: CellError | None = None  # how the last move ended, raised by the next wait()
        self._stop_request: float | None = None  # sim time of a stop() during a move
        options = dict(config.options)
        # 0: never sleep; the environment wins so a test can pace one process of a run (not its record)
        self._realtime = float(
            os.environ.get("CELL_SIM_REALTIME_FACTOR", options.get("sim_realtime_factor", 0.0))
        )
        self._motion_log = os.environ.get("CELL_SIM_MOTION_LOG")  # see the module's docstring
        hz = float(options.get("watchdog_hz", 10.0))
        self.watchdog_period_s: float | None = 1.0 / hz if hz > 0 else None
        self._last_kick = self.clock.now()
        self.command_log: list[dict[str, Any]] = []

    # -------------------------------------------------------------------------------------- contract
    @property
    def envelope(self) -> Envelope:
        return self._envelope

    def connect(self) -> None:
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def state(self) -> RobotState:
        self._update()
        mode = RobotMode.IDLE if self._connected else RobotMode.DISCONNECTED
        return RobotState(
            mode=mode,
            protective_stop=self._protective_stop,
            safeguard_stop=self._safeguard_stop,
            program_running=self._motion is not None,
        )

    def tool_pose(self) -> Array:
        """Current flange pose ``T_B_T`` (mm)."""
        self._require_connected()
        self._update()
        return self.kin.fk(self._q)

    def joints(self) -> Array:
        """Current joint angles (rad)."""
        self._require_connected()
        self._update()
        return self._q.copy()

    def world_tool_pose(self) -> Array:
        """Current flange pose in the world, ``T_W_T = T_W_B @ T_B_T`` (mm), for the simulated camera."""
        return self.T_W_B @ self.tool_pose()

    def stop(self) -> None:
        """Stop any motion now (stopL/stopJ at the configured maximum acceleration). Safe from a signal
        handler or another thread: it only records the request; the polling move decelerates the arm from
        that instant and raises MotionStopped."""
        moving = self._motion is not None
        # recorded when idle too: a move being checked and started right now (start_* clears the request
        # first, then spends wall time on IK and collision checks) must not escape a stop that came meanwhile
        self._stop_request = self.clock.now()
        self._log("stop", None, None, None, 0.0, self.clock.now(), "ok" if moving else "idle")

    def unlock_protective_stop(self) -> None:
        """Clear a latched protective stop, as the UR dashboard's 'unlock protective stop' does."""
        self._require_connected()
        self._protective_stop = False

    def reset_safeguard_stop(self) -> None:
        """The guard is closed again and the safeguard reset input given (a UR's safeguard reset)."""
        self._safeguard_stop = False

    def inject_fault(self, kind: FaultKind, after_s: float | None = None) -> None:
        """Make the next move fail ``after_s`` seconds into its motion (default: half way): a protective
        stop, a lost connection, or a safeguard stop (a guard door opened: the arm decelerates along its
        path, like a category 2 stop, and stays stopped until :meth:`reset_safeguard_stop`)."""
        if kind not in ("protective_stop", "connection_loss", "safeguard_stop"):
            raise ValueError(
                f"unknown fault kind {kind!r}; use 'protective_stop', 'connection_loss' or 'safeguard_stop'"
            )
        self._fault = (kind, after_s)

    def kick_watchdog(self) -> None:
        """Tell the watchdog that the controlling code is alive (ur_rtde's kickWatchdog)."""
        self._last_kick = self.clock.now()

    @property
    def moving(self) -> bool:
        self._update()
        return self._motion is not None

    def wait(self, timeout_s: float = POLL_S) -> bool:
        """Let up to ``timeout_s`` of simulated time pass in the current move, polling every ``POLL_S`` and
        kicking the watchdog at each poll; True when no move is running any more. Raises the move's error
        when it ended in one."""
        deadline = self.clock.now() + timeout_s
        while True:
            self.kick_watchdog()
            m = self._motion
            if m is not None:
                dt = max(
                    0.0, min(POLL_S, deadline - self.clock.now(), m.t0 + m.finish_t() - self.clock.now())
                )
                if self._realtime > 0.0 and dt > 0.0:
                    time.sleep(dt / self._realtime)
                self.clock.advance(dt)
            self._update()
            if self._error is not None:
                error, self._error = self._error, None
                raise error
            if self._motion is None or self.clock.now() >= deadline:
                return self._motion is None

    def _block(self) -> None:
        while not self.wait(POLL_S):
            pass

    def move_linear(self, T_B_T: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float) -> None:
        """Straight-line Cartesian move of the flange to ``T_B_T`` (mm); blocks (polling) until there."""
        self.start_linear(T_B_T, speed_mm_s, accel_mm_s2)
        self._block()

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float) -> None:
        """Joint-space move to ``joints_rad``; blocks (polling) until there."""
        self.start_joint(joints_rad, speed_rad_s, accel_rad_s2)
        self._block()

    def start_linear(self, T_B_T: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float) -> None:
        """Start a straight-line Cartesian move of the flange to ``T_B_T`` (mm), TCP speed/accel
        trapezoid; returns at once (refusals raise before anything moves)."""
        self._stop_request = None
        target = np.array(T_B_T, dtype=np.float64)
        entry = self._log("move_linear", target, speed_mm_s, accel_mm_s2, 0.0, self.clock.now(), "refused")
        self._require_ready()
        self._check_limit(
            "TCP speed", speed_mm_s, self.config.max_tcp_speed_mm_s, "mm/s", "max_tcp_speed_mm_s"
        )
        self._check_limit(
            "TCP acceleration", accel_mm_s2, self.config.max_tcp_accel_mm_s2, "mm/s^2", "max_tcp_accel_mm_s2"
        )
        try:
            check_pose(target)
        except PlanningError as exc:
            raise PlanningError(f"{self.name}: move_linear refused: {exc}") from exc
        self._check_envelope(target[None, :3, 3], "target")
        start = self.kin.fk(self._q)
        dist = float(np.linalg.norm(target[:3, 3] - start[:3, 3]))
        rot = Rotation.from_matrix(np.stack([start[:3, :3], target[:3, :3]]))
        angle = float(np.linalg.norm((rot[0].inv() * rot[1]).as_rotvec()))
        n = max(math.ceil(dist / self._step_mm), math.ceil(angle / self._step_rad), 1) + 1
        u = np.linspace(0.0, 1.0, n)
        poses = np.empty((n, 4, 4))
        poses[:] = np.eye(4)
        poses[:, :3, 3] = start[:3, 3] + u[:, None] * (target[:3, 3] - start[:3, 3])
        poses[:, :3, :3] = Slerp([0.0, 1.0], rot)(u).as_matrix()
        poses[-1] = target
        path = self._follow(poses)
        # Translation at TCP limits; a rotation-dominated move is timed on the wrist at the joint limits.
        t_lin = trapezoid_duration(dist, speed_mm_s, accel_mm_s2)
        t_rot = trapezoid_duration(
            angle, self.config.max_joint_speed_rad_s, self.config.max_joint_accel_rad_s2
        )
        if t_lin >= t_rot:
            s, a_stop = u * dist, self.config.max_tcp_accel_mm_s2
            times = trapezoid_time_at(s, dist, speed_mm_s, accel_mm_s2)
        else:
            s, a_stop = u * angle, self.config.max_joint_accel_rad_s2
            times = trapezoid_time_at(
                s, angle, self.config.max_joint_speed_rad_s, self.config.max_joint_accel_rad_s2
            )
        self._check_joint_rates(path, times)
        self._execute(entry, path, s, times, a_stop)

    def start_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float) -> None:
        """Start a joint-space move to ``joints_rad``; all joints synchronised, the limiting joint sets the
        time; returns at once (refusals raise before anything moves)."""
        self._stop_request = None
        target = np.array(joints_rad, dtype=np.float64).reshape(-1)
        entry = self._log("move_joint", target, speed_rad_s, accel_rad_s2, 0.0, self.clock.now(), "refused")
        self._require_ready()
        self._check_limit(
            "joint speed", speed_rad_s, self.config.max_joint_speed_rad_s, "rad/s", "max_joint_speed_rad_s"
        )
        self._check_limit(
            "joint acceleration",
            accel_rad_s2,
            self.config.max_joint_accel_rad_s2,
            "rad/s^2",
            "max_joint_accel_rad_s2",
        )
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            raise PlanningError(f"{self.name}: move_joint refused: needs 6 finite joint angles, got {target}")
        lo, hi = np.asarray(self.kin.joint_min_rad), np.asarray(self.kin.joint_max_rad)
        if np.any(target < lo) or np.any(target > hi):
            j = int(np.argmax((target < lo) | (target > hi)))
            raise PlanningError(
                f"{self.name}: move_joint refused: joint {j + 1} target {target[j]:.4f} rad is "
                f"outside its limits [{lo[j]:.4f}, {hi[j]:.4f}] rad"
            )
        delta = target - self._q
        span = float(np.max(np.abs(delta)))
        n = max(math.ceil(span / self._step_rad), 1) + 1
        u = np.linspace(0.0, 1.0, n)
        path = self._q + u[:, None] * delta
        path[-1] = target
        self._check_envelope(self.kin.fk(path)[:, :3, 3], "joint path")
        times = trapezoid_time_at(u * span, span, speed_rad_s, accel_rad_s2)
        self._execute(entry, path, u * span, times, self.config.max_joint_accel_rad_s2)

    # -------------------------------------------------------------------------------------- internals
    def _log(
        self,
        command: str,
        target: Array | None,
        speed: float | None,
        accel: float | None,
        duration: float,
        start: float,
        outcome: str,
    ) -> dict[str, Any]:
        entry = {
            "command": command,
            "target": None if target is None else target.copy(),
            "speed": speed,
            "accel": accel,
            "start_s": start,
            "duration_s": duration,
            "outcome": outcome,
            "moved_rad": 0.0,  # set when the move ends: the largest joint's change from start to end
        }
        self.command_log.append(entry)
        return entry

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceFault(self.name, "not connected; call connect() first")

    def _require_ready(self) -> None:
        self._require_connected()
        self._update()
        if self._motion is not None:
            raise DeviceFault(self.name, "refused: a move is still running; wait() for it or stop() it")
        if self._protective_stop:
            raise DeviceFault(
                self.name, "protective stop active; clear the cause, then unlock_protective_stop()"
            )
        if self._safeguard_stop:
            raise DeviceFault(
                self.name, "safeguard stop active (a guard is open); close it and reset the safeguard"
            )

    def _check_limit(self, what: str, value: float, limit: float, unit: str, field: str) -> None:
        if not (math.isfinite(value) and 0.0 < value <= limit):
            raise DeviceFault(
                self.name,
                f"refused: {what} {value} {unit} is outside (0, {limit}] (robot.{field} in the cell config)",
            )

    def _check_envelope(self, points_B: Array, what: str) -> None:
        lo, hi = np.asarray(self._envelope.min_mm), np.asarray(self._envelope.max_mm)
        out = np.any((points_B < lo - 1e-9) | (points_B > hi + 1e-9), axis=1)
        if out.any():
            p = points_B[np.argmax(out)]
            raise PlanningError(
                f"{self.name}: refused: {what} flange position {np.round(p, 1).tolist()} mm "
                f"(base frame) is outside the envelope {lo.tolist()} .. {hi.tolist()} mm"
            )

    def _follow(self, poses: Array) -> Array:
        """IK along sampled poses, each sample on the branch nearest the previous joints (n, 6)."""
        q_all, valid, _ = self.kin.ik_all(poses)
        path = np.empty((len(poses), 6))
        prev = self._q
        for k in range(len(poses)):
            cands = q_all[k][valid[k]]
            if len(cands) == 0:
                where = "target" if k == len(poses) - 1 else f"path sample {k}/{len(poses) - 1}"
                raise PlanningError(
                    f"{self.name}: move_linear refused: {where} unreachable: "
                    f"{self.kin.why_unreachable(poses[k])}"
                )
            shifted, ok = self.kin.shift_into_limits(cands, prev)
            if not ok.any():
                raise PlanningError(
                    f"{self.name}: move_linear refused: path sample {k} violates joint limits"
                )
            shifted = shifted[ok]
            prev = shifted[np.argmin(np.linalg.norm(shifted - prev, axis=1))]
            path[k] = prev
        return path

    def _check_joint_rates(self, path: Array, times: Array) -> None:
        """Refuse paths whose IK-followed joints would exceed the hardware joint speed (singularity)."""
        if len(path) < 2:
            return
        dq = np.abs(np.diff(path, axis=0))
        dt = np.maximum(np.diff(times), 1e-12)
        rate = dq / dt[:, None]
        if rate.max() > UR5E_MAX_JOINT_SPEED_RAD_S:
            k, j = np.unravel_index(np.argmax(rate), rate.shape)
            raise PlanningError(
                f"{self.name}: move_linear refused: joint {j + 1} would need {rate[k, j]:.2f} rad/s "
                f"> {UR5E_MAX_JOINT_SPEED_RAD_S:.2f} rad/s at path sample {k + 1} (singularity or "
                "branch flip); use move_joint or another path"
            )

    def _execute(self, entry: dict[str, Any], path: Array, s: Array, times: Array, a_stop: float) -> None:
        """Start a checked path now: find where a contact or an injected fault would cut it; the arm then
        follows it on the sim clock (:meth:`_update`)."""
        duration = float(times[-1])
        end, outcome = len(path) - 1, "ok"
        error: CellError | None = None
        hits = [
            self._collision.first_contact(self.T_W_B @ self.kin.fk(path)),
            self._collision.arm_contact(self.kin, path, self.T_W_B),
        ]
        contact = min((h for h in hits if h is not None), default=None)
        if contact is not None:
            end = max(contact[0] - 1, 0)
            outcome = "protective_stop"
            error = DeviceFault(
                self.name,
                f"protective stop: {contact[1]}; the arm stopped at the last safe pose. "
                "Move clear, then unlock_protective_stop()",
            )
        if self._fault is not None:
            kind, after = self._fault
            self._fault = None
            t_fault = duration / 2.0 if after is None else min(float(after), duration)
            k_fault = int(np.searchsorted(times, t_fault, side="right") - 1)
            if k_fault < end or error is None:
                end = max(k_fault, 0)
                if kind == "protective_stop":
                    outcome = "protective_stop"
                    error = DeviceFault(
                        self.name, f"protective stop (injected) {t_fault:.3f} s into the move"
                    )
                elif kind == "safeguard_stop":
                    outcome = "safeguard_stop"
                    error = DeviceFault(
                        self.name,
                        f"safeguard stop {t_fault:.3f} s into the move (a guard opened); close the guard, "
                        "reset the safeguard, then `cell resume`",
                    )
                else:
                    outcome = "connection_loss"
                    error = DeviceTimeout(
                        self.name, f"connection lost {t_fault:.3f} s into the move; reconnect"
                    )
        self._error = None
        now = self.clock.now()
        self._last_kick = now
        self._motion = _Motion(
            entry,
            path,
            np.asarray(s, float),
            np.asarray(times, float),
            now,
            end,
            error,
            outcome,
            float(a_stop),
        )
        if self._motion_log:  # the arm is in motion from now: a stop() from here on stops it mid-path
            line = {"command": entry["command"], "target": entry["target"].tolist(), "start_s": now}
            with open(self._motion_log, "a", encoding="utf-8") as f:
                f.write(json.dumps({**line, "duration_s": duration}) + "\n")
        self._update()

    def _update(self) -> None:
        """Bring the arm to the clock's present: apply a stop request or a watchdog trip, finish the move
        when its time is up (latching what its outcome latches)."""
        m = self._motion
        if m is None:
            return
        now = self.clock.now()
        if self._stop_request is not None:
            t_req = max(self._stop_request - m.t0, 0.0)
            self._stop_request = None
            m.begin_stop(
                t_req, MotionStopped(self.name, f"stopped {t_req:.3f} s into the move on request"), "stopped"
            )
        if self.watchdog_period_s is not None and now - self._last_kick > self.watchdog_period_s:
            t_trip = self._last_kick + self.watchdog_period_s - m.t0
            m.begin_stop(
                max(t_trip, 0.0),
                DeviceFault(
                    self.name,
                    f"watchdog: not kicked for {self.watchdog_period_s:.3f} s, motion stopped "
                    f"{max(t_trip, 0.0):.3f} s into the move (the controlling process died or hung)",
                ),
                "watchdog",
            )
        t = now - m.t0
        self._q = m.q_at(min(t, m.finish_t()))
        if now < m.t0 + m.finish_t() - 1e-12:  # compared in absolute time, as wait() advances the clock
            return
        self._motion = None
        m.entry.update(
            duration_s=m.finish_t(), outcome=m.outcome, moved_rad=float(np.max(np.abs(self._q - m.path[0])))
        )
        if m.outcome == "protective_stop":
            self._protective_stop = True
        elif m.outcome == "safeguard_stop":
            self._safeguard_stop = True
        elif m.outcome == "connection_loss":
            self._connected = False
        self._error = m.error
