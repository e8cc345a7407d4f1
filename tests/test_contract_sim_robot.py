"""The Robot contract suite run against the simulated UR5e configured as in the default simulated cell."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import DEFAULT_CELL, load_cell_config
from cell.planning.kinematics import UR5E
from fakes.clock import SimClock
from fakes.robot import SimRobot
from tests.contracts.robot_contract import RobotContract


def sim_cell_robot():
    """The default simulated cell's robot config."""
    return load_cell_config(DEFAULT_CELL).robot


class TestSimRobotContract(RobotContract):
    @pytest.fixture
    def robot(self):
        return SimRobot(sim_cell_robot(), clock=SimClock())

    @pytest.fixture
    def reachable_pose(self, robot):
        """50 mm below and 30 mm aside of the configured home pose, same orientation."""
        T = UR5E.fk(np.deg2rad(robot.config.home_joints_deg))
        T[:3, 3] += [0.0, 30.0, -50.0]
        return T


def test_default_placement_reaches_the_demo_region():
    """Camera (hand-eye T_T_C of sim.yaml) at the stand-off above every point of the demo part region
    (x in [-250, 250], y in [-100, 100], z in [0, 120] mm, world), looking straight down and tilted 40 deg
    toward 8 azimuths, in 4 rolls about the optical axis: every view must be reachable (IK, away from the
    wrist singularity) with the flange inside the envelope."""
    from scipy.spatial.transform import Rotation

    from cell.geometry import invert, make_pose

    cell = load_cell_config(DEFAULT_CELL)
    robot = sim_cell_robot()
    T_T_C, S = cell.sensor.T_T_C.matrix(), cell.sensor.standoff_mm
    pts = np.array([[x, y, z] for x in (-250, 0, 250) for y in (-100, 100) for z in (0, 120)], float)
    views = [(0.0, 0.0)] + [(40.0, az) for az in range(0, 360, 45)]
    T_W_C = []
    for p in pts:
        for tilt, az in views:
            for roll in (0, 90, 180, 270):
                R = Rotation.from_euler("zy", [az, tilt], degrees=True).as_matrix() @ np.diag([1, -1, -1])
                R = R @ Rotation.from_euler("z", roll, degrees=True).as_matrix()
                T_W_C.append(make_pose(R, p - S * R[:, 2]))
    T_B_T = invert(robot.T_W_B.matrix()) @ np.array(T_W_C) @ invert(T_T_C)
    ok = UR5E.reachable_many(T_B_T)
    flange = T_B_T[:, :3, 3]
    inside = np.all((flange >= robot.envelope_min_mm) & (flange <= robot.envelope_max_mm), axis=1)
    assert ok.all() and inside.all()
