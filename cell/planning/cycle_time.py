"""The physical limit of an inspection's cycle time: robot motion along the plan's tour plus pattern capture,
nothing else (no computing, no communication overheads).

Motion: each move from one view to the next (from home to the first view and from the last view back home)
takes at least as long as the slowest of its axes needs under a trapezoidal velocity profile (accelerate at
the limit, cruise at the limit, brake at the limit): the tool centre point's straight-line distance under
the cell's TCP speed and acceleration limits, and each joint's angle change (inverse kinematics nearest to
the previous configuration, as the cell moves) under the joint limits. A real path is never shorter than the
straight line in either space, so this is a lower bound the cell can approach but not beat.

Capture: per view, the display latency once (the first pattern's light arrives that long after it is sent),
then one frame period per pattern: the slowest of the display refresh, the camera's frame rate when
configured and the exposure.

Units: seconds, millimetres, radians.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config import CellConfig

DEFAULT_REFRESH_HZ = 60.0  # the projectors we build on show patterns over HDMI at 60 Hz


def trapezoid_time(distance: float, v_max: float, a_max: float) -> float:
    """Shortest time (s) to travel ``distance`` from rest to rest with |v| <= v_max and |a| <= a_max.

    Triangle profile when the distance is too short to reach v_max (d < v_max^2 / a_max)."""
    d = abs(float(distance))
    if d == 0.0:
        return 0.0
    if d < v_max * v_max / a_max:
        return 2.0 * math.sqrt(d / a_max)
    return d / v_max + v_max / a_max


@dataclass(frozen=True)
class CaptureTiming:
    """How long one view's pattern sequence takes: ``latency_s + n_frames * frame_period_s``."""

    n_frames: int
    frame_period_s: float
    latency_s: float
    limited_by: str  # what sets the frame period: "display refresh", "camera frame rate" or "exposure"

    @property
    def seconds(self) -> float:
        return self.latency_s + self.n_frames * self.frame_period_s

    @classmethod
    def from_config(cls, cfg: CellConfig, n_frames: int) -> CaptureTiming:
        """From the cell config: the projector's display refresh (``projector.options.display.refresh_hz``,
        default 60 Hz) and latency (``...display.latency_ms``, default 0), the camera's frame rate
        (``camera.options.frame_rate_hz``, when set) and exposure."""
        display = cfg.sensor.projector.options.get("display") or {}
        camera = cfg.sensor.camera
        periods = {
            "display refresh": 1.0 / float(display.get("refresh_hz", DEFAULT_REFRESH_HZ)),
            "exposure": camera.exposure_ms / 1000.0,
        }
        if camera.options.get("frame_rate_hz"):
            periods["camera frame rate"] = 1.0 / float(camera.options["frame_rate_hz"])
        limited_by = max(periods, key=lambda k: periods[k])
        return cls(n_frames, periods[limited_by], float(display.get("latency_ms", 0.0)) / 1000.0, limited_by)


@dataclass(frozen=True)
class MoveTime:
    """The limit of one move: the straight TCP distance, the largest joint change and the time they need."""

    start: str
    end: str
    tcp_mm: float
    joint_rad: float
    seconds: float
    limited_by: str  # "tcp" or "joint k" (0-based)


@dataclass(frozen=True)
class CycleTime:
    """Motion and capture limit of a whole tour, with the per-move breakdown."""

    moves: list[MoveTime]
    capture: CaptureTiming
    n_views: int

    @property
    def motion_s(self) -> float:
        return float(sum(m.seconds for m in self.moves))

    @property
    def capture_s(self) -> float:
        return self.n_views * self.capture.seconds

    @property
    def total_s(self) -> float:
        return self.motion_s + self.capture_s

    def to_json(self) -> dict[str, Any]:
        return {
            "total_s": self.total_s,
            "motion_s": self.motion_s,
            "capture_s": self.capture_s,
            "views": self.n_views,
            "capture_per_view_s": self.capture.seconds,
            "frames_per_view": self.capture.n_frames,
            "frame_period_s": self.capture.frame_period_s,
            "frame_period_limited_by": self.capture.limited_by,
            "display_latency_s": self.capture.latency_s,
            "moves": [m.__dict__ for m in self.moves],
        }

    def summary(self) -> str:
        """A few lines for the terminal: the total and its breakdown."""
        c = self.capture
        slowest = max(self.moves, key=lambda m: m.seconds) if self.moves else None
        lines = [
            f"cycle-time limit {self.total_s:.2f} s = motion {self.motion_s:.2f} s + capture "
            f"{self.capture_s:.2f} s (computing not included)",
            f"  capture: {self.n_views} views x ({c.n_frames} frames x {1000 * c.frame_period_s:.1f} ms, "
            f"set by {c.limited_by}, + {1000 * c.latency_s:.0f} ms display latency) = "
            f"{c.seconds:.3f} s per view",
            f"  motion: {len(self.moves)} moves (home -> views -> home) under the TCP and joint limits",
        ]
        if slowest is not None:
            lines.append(
                f"  slowest move {slowest.start} -> {slowest.end}: {slowest.seconds:.2f} s "
                f"({slowest.tcp_mm:.0f} mm, {math.degrees(slowest.joint_rad):.0f} deg, set by "
                f"{slowest.limited_by})"
            )
        return "\n".join(lines)


def move_time(
    T_a: NDArray, T_b: NDArray, q_a: NDArray, q_b: NDArray, cfg: CellConfig, start: str, end: str
) -> MoveTime:
    """Limit of one move between flange poses ``T_B_T`` (4x4, mm) with joint configurations (6,) rad."""
    r = cfg.robot
    tcp = float(np.linalg.norm(np.asarray(T_b)[:3, 3] - np.asarray(T_a)[:3, 3]))
    dq = np.abs(np.asarray(q_b, dtype=np.float64) - np.asarray(q_a, dtype=np.float64))
    times = {"tcp": trapezoid_time(tcp, r.max_tcp_speed_mm_s, r.max_tcp_accel_mm_s2)}
    for k, d in enumerate(dq):
        times[f"joint {k}"] = trapezoid_time(d, r.max_joint_speed_rad_s, r.max_joint_accel_rad_s2)
    limited_by = max(times, key=lambda k: times[k])
    return MoveTime(start, end, tcp, float(dq.max()), times[limited_by], limited_by)


def cycle_time(cfg: CellConfig, tour_T_B_T: Sequence[NDArray], n_frames: int) -> CycleTime:
    """Limit of visiting the flange poses ``tour_T_B_T`` (robot base frame, in order) from the home
    configuration and back, capturing ``n_frames`` patterns at each."""
    from cell.planning.kinematics import UR5E

    q_home = np.radians(cfg.robot.home_joints_deg)
    T_home = UR5E.fk(q_home)
    names = ["home"] + [f"view {k}" for k in range(len(tour_T_B_T))] + ["home"]
    poses, joints = [T_home], [q_home]
    for T in tour_T_B_T:
        joints.append(UR5E.ik_nearest(T, joints[-1]))
        poses.append(np.asarray(T))
    if tour_T_B_T:
        poses.append(T_home)
        joints.append(q_home)
    moves = [
        move_time(poses[i], poses[i + 1], joints[i], joints[i + 1], cfg, names[i], names[i + 1])
        for i in range(len(poses) - 1)
    ]
    return CycleTime(moves, CaptureTiming.from_config(cfg, n_frames), len(tour_T_B_T))


def inspection_frames(cfg: CellConfig) -> int:
    """Patterns per view of ``cell inspect`` on this cell (the GCLS set cell/inspection.py projects)."""
    from cell.sensing.patterns import measuring_patterns

    return len(measuring_patterns(cfg.sensor.projector).frames)
