"""Simulated UR5e: reaches targets, times motions by the trapezoid formula, refuses with reasons, and
protective-stops on contact with the table or an obstacle (truth: analytic geometry and timing)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cell.config import RobotConfig
from cell.contracts import RobotMode
from cell.errors import DeviceFault, DeviceTimeout, MotionStopped, PlanningError
from cell.geometry import make_pose
from cell.planning.kinematics import UR5E
from fakes.clock import SimClock
from fakes.robot import SimRobot

DOWN = np.diag([1.0, -1.0, -1.0])  # flange z pointing down (-z of base and world here)
BODY = np.array([[x, y, z] for x in (-60, 60) for y in (-60, 60) for z in (0, 100)], float)  # sensor box, {T}


def _config(**kw) -> RobotConfig:
    base = dict(
        name="arm1",
        T_W_B={"xyz_mm": (0, 0, 0)},
        envelope_min_mm=(-900, -900, -100),
        envelope_max_mm=(900, 900, 1000),
        max_tcp_speed_mm_s=250,
        max_tcp_accel_mm_s2=1200,
        max_joint_speed_rad_s=1.05,
        max_joint_accel_rad_s2=3.0,
        home_joints_deg=(0, -90, 90, -90, -90, 0),
    )
    base.update(kw)
    return RobotConfig(**base)


def _robot(**kw) -> SimRobot:
    r = SimRobot(_config(), clock=SimClock(), **kw)
    r.connect()
    return r


def _down(x, y, z) -> np.ndarray:
    return make_pose(DOWN, (x, y, z))


def _trap(d, v, a):
    return d / v + v / a if d >= v * v / a else 2 * np.sqrt(d / a)


def test_linear_move_reaches_target_and_follows_a_straight_line():
    r = _robot()
    target = _down(-500, -250, 250)
    r.move_linear(target, 200, 1000)
    assert np.linalg.norm(r.tool_pose()[:3, 3] - target[:3, 3]) < 1e-6
    np.testing.assert_allclose(UR5E.fk(r.joints()), target, atol=1e-6)
    assert r.state().normal


@pytest.mark.parametrize("dist", [300.0, 20.0])  # cruise (d > v^2/a = 52 mm) and triangular profile
def test_linear_motion_time_is_the_trapezoid(dist):
    r = _robot()
    start = r.tool_pose()
    target = start.copy()
    target[:3, 3] += dist * np.array([0.0, -0.6, -0.8])
    t0 = r.clock.now()
    r.move_linear(target, 250, 1200)
    assert r.clock.now() - t0 == pytest.approx(_trap(dist, 250, 1200), rel=1e-9)
    assert r.command_log[-1]["duration_s"] == pytest.approx(_trap(dist, 250, 1200), rel=1e-9)


def test_joint_motion_time_is_set_by_the_limiting_joint():
    r = _robot()
    q0 = r.joints()
    target = q0 + np.array([0.2, -0.4, 1.3, 0.1, 0.05, -0.02])
    t0 = r.clock.now()
    r.move_joint(target, 1.0, 3.0)
    np.testing.assert_allclose(r.joints(), target, atol=1e-12)
    assert r.clock.now() - t0 == pytest.approx(_trap(1.3, 1.0, 3.0), rel=1e-9)


def test_refusals_say_why_and_move_nothing():
    r = _robot()
    q0 = r.joints()
    with pytest.raises(PlanningError, match="arm1.*envelope"):
        r.move_linear(_down(-500, 0, -150), 100, 500)
    with pytest.raises(PlanningError, match="arm1.*out of reach"):
        r.move_linear(_down(-880, 0, 600), 100, 500)
    with pytest.raises(DeviceFault, match="arm1.*max_tcp_speed_mm_s"):
        r.move_linear(_down(-500, 0, 300), 300, 500)
    with pytest.raises(DeviceFault, match="max_joint_accel_rad_s2"):
        r.move_joint(q0, 0.5, 10.0)
    with pytest.raises(PlanningError, match="joint 2 .*limits"):
        r.move_joint(q0 + np.array([0, -7, 0, 0, 0, 0]), 0.5, 1.0)
    np.testing.assert_array_equal(r.joints(), q0)
    assert [e["outcome"] for e in r.command_log] == ["refused"] * 5
    r.close()
    with pytest.raises(DeviceFault, match="not connected"):
        r.move_joint(q0, 0.5, 1.0)
    assert r.state().mode is RobotMode.DISCONNECTED


def test_path_through_the_base_column_is_refused():
    r = _robot()
    r.move_linear(_down(-400, -50, 300), 200, 1000)
    with pytest.raises(PlanningError, match="path sample .*base axis"):
        r.move_linear(_down(300, -50, 300), 200, 1000)  # passes 50 mm from joint 1, needs >= d4 = 133.3


def test_joint_path_leaving_the_envelope_is_refused():
    r = SimRobot(_config(envelope_max_mm=(900, 900, 600)), clock=SimClock())
    r.connect()
    with pytest.raises(PlanningError, match="joint path .*envelope"):
        r.move_joint(np.deg2rad([0, -90, 0, -90, -90, 0]), 1.0, 3.0)  # forearm straight up: flange z ~ 880


def test_table_contact_triggers_protective_stop_at_last_safe_pose():
    r = _robot(tool_body_T=BODY)
    r.move_linear(_down(-500, -200, 300), 250, 1200)
    with pytest.raises(DeviceFault, match="arm1: protective stop: tool body point .* table"):
        r.move_linear(_down(-500, -200, 50), 250, 1200)  # box bottom reaches 50 - 100 = -50 mm
    assert r.state().protective_stop and not r.state().normal
    z_low = r.tool_pose()[2, 3] - 100.0
    assert 0.0 <= z_low <= 2.0 + 1e-9  # stopped within one 2 mm path sample above the table
    assert r.command_log[-1]["outcome"] == "protective_stop"
    with pytest.raises(DeviceFault, match="protective stop active"):
        r.move_linear(_down(-500, -200, 300), 100, 500)
    r.unlock_protective_stop()
    r.move_linear(_down(-500, -200, 300), 100, 500)
    assert r.state().normal


def test_obstacle_contact_triggers_protective_stop():
    box = trimesh.creation.box(extents=(200, 200, 100), transform=make_pose(None, (-500, -200, 50)))
    r = _robot(obstacles_W=box, tool_body_T=BODY)
    r.move_linear(_down(-500, -200, 400), 250, 1200)
    with pytest.raises(DeviceFault, match="obstacle"):
        r.move_linear(_down(-500, -200, 150), 250, 1200)  # box top at 100, sensor bottom would reach 50
    assert r.state().protective_stop
    z_low = r.tool_pose()[2, 3] - 100.0
    assert 100.0 <= z_low <= 102.0 + 1e-9


def test_obstacle_between_the_tool_corners_is_caught():
    spike = trimesh.creation.box(extents=(10, 10, 300), transform=make_pose(None, (-500, -200, 150)))
    r = _robot(obstacles_W=spike, tool_body_T=BODY)
    r.move_linear(_down(-500, -200, 500), 250, 1200)
    with pytest.raises(DeviceFault, match="tool body hits"):
        r.move_linear(_down(-500, -200, 380), 250, 1200)  # spike top at 300, sensor bottom would reach 280
    assert 300.0 <= r.tool_pose()[2, 3] - 100.0 <= 302.0 + 1e-9


def test_injected_faults_stop_the_next_move_midway():
    r = _robot()
    r.inject_fault("protective_stop", after_s=0.5)
    t0 = r.clock.now()
    with pytest.raises(DeviceFault, match="injected"):
        r.move_linear(_down(-500, -250, 250), 200, 1000)
    assert 0.49 <= r.clock.now() - t0 <= 0.5 and r.state().protective_stop
    r.unlock_protective_stop()
    r.inject_fault("connection_loss")
    with pytest.raises(DeviceTimeout, match="connection lost"):
        r.move_joint(r.joints() + 0.3, 1.0, 3.0)
    assert r.state().mode is RobotMode.DISCONNECTED
    r.connect()
    r.move_joint(r.joints() + 0.1, 1.0, 3.0)  # the fault fired once only
    assert r.command_log[-1]["outcome"] == "ok"


def test_command_log_records_what_was_commanded():
    r = _robot()
    r.move_linear(_down(-500, -250, 250), 200, 1000)
    r.stop()
    log = r.command_log
    assert [e["command"] for e in log] == ["move_linear", "stop"]
    assert log[0]["speed"] == 200 and log[0]["accel"] == 1000 and log[0]["start_s"] == 0.0
    np.testing.assert_array_equal(log[0]["target"], _down(-500, -250, 250))


def test_linear_path_through_the_wrist_singularity_is_refused():
    qa = np.array([-0.3, -1.2, 1.0, -0.5, 0.03, 0.7])  # q5 = +0.03 rad ...
    qb = qa + np.array([0.05, 0, 0, 0, -0.06, 0])  # ... to q5 = -0.03: the straight line crosses q5 = 0
    r = _robot()
    r.move_joint(qa, 1.0, 3.0)
    with pytest.raises(PlanningError, match="joint 4 would need .* rad/s"):
        r.move_linear(UR5E.fk(qb), 250, 1200)
    np.testing.assert_allclose(r.joints(), qa)


def _start_far_linear(r: SimRobot) -> tuple[np.ndarray, np.ndarray]:
    start = r.tool_pose()
    target = start.copy()  # same orientation: the move is timed on its 265 mm translation
    target[:3, 3] = (-500, -250, 250)
    r.start_linear(target, 200, 1000)
    return start, target


def test_stop_mid_move_decelerates_from_the_speed_at_that_instant():
    """Truth: a 1-D trapezoid. A stop at time t during the cruise (v = 200 mm/s) ends v/a = 1200 mm/s^2
    later, v^2 / 2a further along the straight line, and the move raises MotionStopped."""
    r = _robot()
    start, target = _start_far_linear(r)
    d = np.linalg.norm(target[:3, 3] - start[:3, 3])
    assert r.moving and r.state().program_running
    assert not r.wait(0.5)  # cruising from 0.2 s on
    r.stop()
    with pytest.raises(MotionStopped, match="0.500 s into the move"):
        while not r.wait(0.004):
            pass
    # 0.2 s accelerating at 1000 (20 mm), 0.3 s cruising (60 mm), then stopping at 1200 mm/s^2 (16.7 mm)
    s_expected = 0.5 * 1000 * 0.2**2 + 0.3 * 200 + 200**2 / (2 * 1200)
    p = r.tool_pose()[:3, 3]
    # joints are interpolated between 2 mm path samples: the chord leaves the line by far less than 1 um
    assert np.linalg.norm(p - start[:3, 3]) == pytest.approx(s_expected, abs=1e-3)
    assert (
        np.linalg.norm(np.cross(p - start[:3, 3], target[:3, 3] - start[:3, 3])) / d < 5e-3
    )  # on the line (within the chord error)
    assert r.command_log[0]["outcome"] == "stopped"
    assert r.command_log[0]["duration_s"] == pytest.approx(0.5 + 200 / 1200, abs=1e-9)
    r.move_linear(target, 200, 1000)  # usable again at once: a stop on request latches nothing
    assert np.linalg.norm(r.tool_pose()[:3, 3] - target[:3, 3]) < 1e-6


def test_watchdog_stops_the_arm_one_period_after_the_last_kick():
    r = _robot()
    start, target = _start_far_linear(r)
    r.wait(0.5)  # polled (and kicked) until 0.5 s
    r.kick_watchdog()  # the last sign of life, at 0.5 s
    r.clock.advance(5.0)  # then nobody polls: the process died; the world goes on
    assert not r.moving
    entry = r.command_log[0]
    assert entry["outcome"] == "watchdog"
    assert entry["duration_s"] == pytest.approx(0.5 + 0.1 + 200 / 1200, abs=1e-9)
    with pytest.raises(DeviceFault, match="watchdog"):
        r.wait()
    assert np.linalg.norm(r.tool_pose()[:3, 3] - target[:3, 3]) > 100.0


def test_stop_requested_while_a_move_is_being_checked_stops_it_at_once():
    """A signal can arrive while start_linear computes its path (wall time, no sim time): the move must not
    run to its end."""
    r = _robot()
    checks = r._check_joint_rates

    def slow_check(path, times):
        r.stop()  # the signal handler runs here
        return checks(path, times)

    r._check_joint_rates = slow_check
    start = r.tool_pose()
    with pytest.raises(MotionStopped):
        r.move_linear(_down(-500, -250, 250), 200, 1000)
    np.testing.assert_allclose(r.tool_pose(), start, atol=1e-9)
