"""The cycle-time model against analytic cases: trapezoid and triangle profiles, the frame period, a tour."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.config import DEFAULT_CELL, load_cell_config
from cell.planning.cycle_time import CaptureTiming, cycle_time, inspection_frames, move_time, trapezoid_time
from cell.planning.kinematics import UR5E

CFG = load_cell_config(DEFAULT_CELL)


def test_trapezoid_profile_cruises_at_the_speed_limit() -> None:
    # 1000 mm at 250 mm/s, 500 mm/s^2: 0.5 s up to speed (62.5 mm), 3.5 s cruise (875 mm), 0.5 s down
    assert trapezoid_time(1000.0, 250.0, 500.0) == pytest.approx(4.5)


def test_short_moves_are_triangles_and_the_two_profiles_meet() -> None:
    # 50 mm at 500 mm/s^2 never reaches 250 mm/s: 25 mm accelerating (0.316 s) and 25 mm braking
    assert trapezoid_time(50.0, 250.0, 500.0) == pytest.approx(2 * math.sqrt(25.0 * 2 / 500.0))
    edge = 250.0**2 / 500.0  # the distance at which the peak speed just touches the limit
    assert trapezoid_time(edge * (1 - 1e-12), 250.0, 500.0) == pytest.approx(
        trapezoid_time(edge, 250.0, 500.0)
    )
    assert trapezoid_time(0.0, 1.0, 1.0) == 0.0 and trapezoid_time(-1000.0, 250.0, 500.0) == pytest.approx(
        4.5
    )


def test_a_move_takes_as_long_as_its_slowest_axis() -> None:
    r = CFG.robot
    q = np.radians(r.home_joints_deg)
    T = UR5E.fk(q)
    T2 = T.copy()
    T2[:3, 3] += (600.0, 0.0, 0.0)
    lin = move_time(T, T2, q, q, CFG, "a", "b")  # the joints barely matter: the TCP limit sets it
    assert lin.limited_by == "tcp" and lin.seconds == pytest.approx(
        600 / r.max_tcp_speed_mm_s + r.max_tcp_speed_mm_s / r.max_tcp_accel_mm_s2
    )
    q2 = q.copy()
    q2[5] += math.pi  # a wrist turn in place: no TCP travel, joint 5 sets the time
    turn = move_time(T, T, q, q2, CFG, "a", "b")
    expect = math.pi / r.max_joint_speed_rad_s + r.max_joint_speed_rad_s / r.max_joint_accel_rad_s2
    assert turn.limited_by == "joint 5" and turn.seconds == pytest.approx(expect)


def test_frame_period_is_the_slowest_of_refresh_camera_and_exposure() -> None:
    base = CaptureTiming.from_config(CFG, 38)
    assert base.limited_by == "display refresh" and base.frame_period_s == pytest.approx(1 / 60)
    assert base.seconds == pytest.approx(38 / 60)  # the 0.63 s per view
    cfg = CFG.model_copy(deep=True)
    cfg.sensor.camera.exposure_ms = 40.0
    assert CaptureTiming.from_config(cfg, 10).frame_period_s == pytest.approx(0.040)
    cfg.sensor.camera.options["frame_rate_hz"] = 10.0
    cfg.sensor.projector.options["display"] = {"refresh_hz": 120.0, "latency_ms": 50.0}
    t = CaptureTiming.from_config(cfg, 10)
    assert t.limited_by == "camera frame rate" and t.seconds == pytest.approx(0.05 + 10 * 0.1)


def test_a_tour_from_home_and_back_adds_its_moves_and_captures() -> None:
    q = np.radians(CFG.robot.home_joints_deg)
    T_home = UR5E.fk(q)
    up = T_home.copy()
    up[:3, 3] += (0.0, 0.0, -100.0)
    limit = cycle_time(CFG, [up, T_home], 38)
    assert [(m.start, m.end) for m in limit.moves] == [
        ("home", "view 0"),
        ("view 0", "view 1"),
        ("view 1", "home"),
    ]
    one = trapezoid_time(100.0, CFG.robot.max_tcp_speed_mm_s, CFG.robot.max_tcp_accel_mm_s2)
    assert limit.moves[0].seconds >= one and limit.moves[2].seconds == 0.0
    assert limit.moves[0].seconds == pytest.approx(limit.moves[1].seconds)  # there and back again
    assert limit.total_s == pytest.approx(limit.motion_s + 2 * 38 / 60)
    assert "cycle-time limit" in limit.summary() and limit.to_json()["views"] == 2


def test_the_inspection_pattern_set_has_38_frames_on_the_prototype() -> None:
    assert inspection_frames(CFG) == 38  # white, black, 6 Gray + 12 shifts, each with its inverse
