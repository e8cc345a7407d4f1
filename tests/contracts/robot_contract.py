"""Contract every :class:`cell.contracts.Robot` implementation passes (simulated, real driver on a fake
controller, replay). Use it as a mixin::

    class TestMyRobot(RobotContract):
        @pytest.fixture
        def robot(self): return MyRobot(...)          # not yet connected
        @pytest.fixture
        def reachable_pose(self): return T_B_T         # a pose this robot can reach from where it starts

Override the class attributes when the implementation needs gentler motion or looser tolerances.
"""

from __future__ import annotations

import numpy as np
import pytest

from cell.contracts import Envelope, Robot, RobotMode
from cell.errors import CellError


class RobotContract:
    speed_mm_s = 50.0  # slow enough for any configured limit
    accel_mm_s2 = 200.0
    joint_speed_rad_s = 0.3
    joint_accel_rad_s2 = 1.0
    pose_tol_mm = 0.03  # the arm's pose repeatability (UR5e: +-0.03 mm, ISO 9283); no arm meets 1 um

    def test_is_a_robot(self, robot):
        assert isinstance(robot, Robot)
        assert isinstance(robot.name, str) and robot.name
        assert isinstance(robot.envelope, Envelope)

    def test_connect_state_close(self, robot):
        robot.connect()
        try:
            state = robot.state()
            assert state.normal and not state.protective_stop and not state.emergency_stop
        finally:
            robot.close()
        assert robot.state().mode is RobotMode.DISCONNECTED

    def test_pose_and_joints_agree_in_shape_and_rigidity(self, robot):
        robot.connect()
        try:
            T = np.asarray(robot.tool_pose())
            q = np.asarray(robot.joints())
            assert T.shape == (4, 4) and q.shape == (6,)
            np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6)
            np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        finally:
            robot.close()

    def test_move_linear_reaches_the_pose(self, robot, reachable_pose):
        robot.connect()
        try:
            robot.move_linear(reachable_pose, self.speed_mm_s, self.accel_mm_s2)
            T = robot.tool_pose()
            assert np.linalg.norm(T[:3, 3] - reachable_pose[:3, 3]) < self.pose_tol_mm
            np.testing.assert_allclose(T[:3, :3], reachable_pose[:3, :3], atol=1e-6)
            assert robot.state().normal
        finally:
            robot.close()

    def test_move_joint_returns_to_the_start(self, robot, reachable_pose):
        robot.connect()
        try:
            q0 = np.asarray(robot.joints()).copy()
            robot.move_linear(reachable_pose, self.speed_mm_s, self.accel_mm_s2)
            robot.move_joint(q0, self.joint_speed_rad_s, self.joint_accel_rad_s2)
            np.testing.assert_allclose(robot.joints(), q0, atol=1e-6)
        finally:
            robot.close()

    def test_stop_leaves_the_robot_usable(self, robot, reachable_pose):
        robot.connect()
        try:
            robot.stop()
            assert robot.state().normal
            robot.move_linear(reachable_pose, self.speed_mm_s, self.accel_mm_s2)
        finally:
            robot.close()

    def test_refuses_a_pose_outside_the_envelope(self, robot, reachable_pose):
        robot.connect()
        try:
            before = np.asarray(robot.tool_pose()).copy()
            outside = np.array(reachable_pose, dtype=np.float64)
            outside[0, 3] = robot.envelope.max_mm[0] + 100.0
            with pytest.raises(CellError):
                robot.move_linear(outside, self.speed_mm_s, self.accel_mm_s2)
            np.testing.assert_allclose(robot.tool_pose(), before, atol=self.pose_tol_mm)
        finally:
            robot.close()
