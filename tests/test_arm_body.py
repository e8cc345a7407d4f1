"""The arm's link capsules: where UR's published UR5e geometry puts the links, and the clearance check that
sees a post next to the upper arm which the sensor-body check cannot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.config import load_cell_config
from cell.errors import DeviceFault, PlanningError
from cell.planning.arm_body import arm_samples
from cell.planning.kinematics import UR5E
from cell.planning.motion import MotionPlanner
from cell.planning.reach import ReachChecker
from fakes.robot import SimRobot

SIM = Path(__file__).resolve().parent.parent / "recipes" / "cells" / "sim.yaml"
HOME = np.deg2rad([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


def _link(samples, name: str) -> np.ndarray:
    return samples.points_B[0][[i for i, n in enumerate(samples.link) if n == name]]


def test_links_at_the_zero_pose_where_the_ur5e_drawing_puts_them() -> None:
    """At zero joints the UR5e lies along -x: shoulder 162.5 mm up, upper arm 425 mm long and 138 mm out
    along -y, forearm 392.2 mm long 7 mm out (138 - 131), wrist 1 housing up to 133.3 mm out."""
    s = arm_samples(UR5E, np.zeros(6))
    upper, fore, wrist = _link(s, "upper arm"), _link(s, "forearm"), _link(s, "wrist 1")
    assert np.allclose(upper[:, 1:], (-138.0, 162.5)) and np.allclose(upper[[0, -1], 0], (0.0, -425.0))
    assert np.allclose(fore[:, 1:], (-7.0, 162.5)) and np.allclose(fore[[0, -1], 0], (-425.0, -817.2))
    assert np.allclose(wrist[:, [0, 2]], (-817.2, 162.5)) and np.allclose(wrist[[0, -1], 1], (-7, -133.3))
    assert np.diff(upper[:, 0]).max() < 0 and np.abs(np.diff(upper[:, 0])).max() <= 20.0 + 1e-9


def test_a_post_beside_the_upper_arm_blocks_the_arm_but_not_the_sensor() -> None:
    """At home the upper arm stands vertical on the axis x = 0, y = -138 mm of {B}, from 162.5 to 587.5 mm
    up. A post whose face is 80 mm from that axis leaves 20 mm to the 60 mm arm hull: too close for a 30 mm
    clearance. 270 mm away it is clear."""
    cfg = load_cell_config(SIM)
    T_W_B = cfg.robot.T_W_B.matrix()

    def checker(offset_x_mm: float) -> ReachChecker:
        post = trimesh.creation.box(extents=(60.0, 60.0, 300.0))
        post.apply_translation((offset_x_mm, -138.0, 375.0))  # in {B}, beside the upper arm's middle
        post.apply_transform(T_W_B)
        samples = np.vstack([post.vertices, post.sample(20000, seed=1)])
        return ReachChecker(cfg, samples, clearance_mm=30.0)

    near, far = checker(110.0), checker(300.0)  # post faces 80 mm and 270 mm from the arm's axis
    flange = UR5E.fk(HOME)[None]
    assert near.path_clear(flange) == (True, "clear")  # the sensor is nowhere near the post
    ok, why = near.arm_clear(HOME[None])
    assert not ok and "upper arm" in why and "from the part" in why
    # 80 mm from the axis minus the 60 mm hull; the samples of the post's face are at least that far
    assert 20.0 <= float(why.split("upper arm ")[1].split(" mm")[0]) < 23.0
    assert far.arm_clear(HOME[None]) == (True, "clear")


def test_a_low_arm_is_refused_by_the_table() -> None:
    """Stretched out flat at zero joints the arm is at base height: on the sim cell's 300 mm pedestal the
    upper arm's hull is 300 + 162.5 - 60 mm above the table; lowered 450 mm it is below it."""
    cfg = load_cell_config(SIM)
    assert cfg.robot.T_W_B.matrix()[2, 3] == 300.0
    part = np.array([[2000.0, 2000.0, 0.0]])  # far away: only the table matters
    assert ReachChecker(cfg, part, clearance_mm=30.0).arm_clear(np.zeros((1, 6)))[0]
    low = cfg.model_copy(deep=True)
    low.robot.T_W_B.xyz_mm = (*cfg.robot.T_W_B.xyz_mm[:2], -150.0)
    ok, why = ReachChecker(low, part, clearance_mm=30.0).arm_clear(np.zeros((1, 6)))
    assert not ok and "above the table" in why


def test_motion_planner_refuses_to_swing_the_arm_through_a_post() -> None:
    """Turning the base 90 deg from home swings the vertical upper arm (138 mm from the base axis) through
    45 deg, where a thin post stands on its axis; at both ends the post is 2 * 138 * sin(22.5 deg) = 105.6 mm
    from the arm's axis, clear of its hull. Every path option must be refused for the arm, and the same turn
    without the post is planned."""
    cfg = load_cell_config(SIM)
    T_W_B = cfg.robot.T_W_B.matrix()
    goal_q = HOME + np.deg2rad([90.0, 0, 0, 0, 0, 0])
    mid = np.deg2rad(45.0)

    def planner(with_post: bool) -> MotionPlanner:
        post = trimesh.creation.box(extents=(20.0, 20.0, 300.0))
        post.apply_translation((138.0 * np.sin(mid), -138.0 * np.cos(mid), 375.0))
        if not with_post:
            post.apply_translation((0.0, 0.0, 5000.0))  # far above the robot's reach
        post.apply_transform(T_W_B)
        points = np.vstack([post.vertices, post.sample(5000, seed=2)])
        reach = ReachChecker(cfg, points, clearance_mm=30.0)
        assert reach.arm_clear(np.stack([HOME, goal_q]))[0]  # both ends are clear
        return MotionPlanner(reach, UR5E, lift_mm=80.0, z_max_mm=1500.0, tcp_speed_mm_s=250.0)

    start, goal = UR5E.fk(HOME), UR5E.fk(goal_q)
    with pytest.raises(PlanningError, match="no collision-free path") as err:
        planner(with_post=True).plan(start, HOME, goal, q_home=HOME)
    assert "robot upper arm" in str(err.value)
    moves, _ = planner(with_post=False).plan(start, HOME, goal, q_home=HOME)
    assert moves


def test_simulated_robot_stops_when_its_upper_arm_meets_a_post() -> None:
    """The simulator is the independent truth for link contact (exact distance to the post's mesh, not the
    planner's surface samples): turning the base through the post of the planner test stops the arm with a
    protective stop before 45 deg, naming the upper arm; without the post the same move completes."""
    cfg = load_cell_config(SIM)
    T_W_B = cfg.robot.T_W_B.matrix()
    mid = np.deg2rad(45.0)
    post = trimesh.creation.box(extents=(20.0, 20.0, 300.0))
    post.apply_translation((138.0 * np.sin(mid), -138.0 * np.cos(mid), 375.0))
    post.apply_transform(T_W_B)
    goal = HOME + np.deg2rad([90.0, 0, 0, 0, 0, 0])
    speed, accel = cfg.robot.max_joint_speed_rad_s, cfg.robot.max_joint_accel_rad_s2

    blocked = SimRobot(cfg.robot, obstacles_W=post)
    blocked.connect()
    with pytest.raises(DeviceFault, match="protective stop: robot upper arm touches the obstacle mesh"):
        blocked.move_joint(goal, speed, accel)
    assert blocked.state().protective_stop
    # the upper arm's hull (60 mm) meets the 20 mm post whose centre is 45 deg round: the axis 70 mm away
    # from the centre, i.e. 2 * 138 * sin(delta / 2) = 70 mm -> delta = 29.4 deg before it
    turned = np.rad2deg(blocked.joints()[0] - HOME[0])
    assert 10.0 < turned < 45.0 - 25.0

    free = SimRobot(cfg.robot)
    free.connect()
    free.move_joint(goal, speed, accel)
    assert np.allclose(free.joints(), goal)
