"""URRobot through the real ur_rtde client against the fake UR controller (fakes/ur_controller.py) on its own
127.0.N.M loopback address per test: the Robot contract, unit conversion, limits and fault cases."""

from __future__ import annotations

import itertools
import multiprocessing
import os
import socket
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.config import RobotConfig
from cell.errors import DeviceFault, DeviceTimeout, PlanningError
from cell.geometry import pose_from_xyz_rpy
from drivers.ur_robot import URRobot
from fakes.ur_controller import FakeURController
from tests.contracts.robot_contract import RobotContract

pytestmark = pytest.mark.timeout(30)
FACING_X = (np.pi, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)  # flange in front of the base (+x)
_hosts = itertools.count(2)


def fresh_host() -> str:
    return f"127.0.{os.getpid() % 250 + 1}.{next(_hosts)}"


def robot_config(host: str) -> RobotConfig:
    return RobotConfig(
        driver="ur_rtde",
        name="ur5e",
        host=host,
        envelope_min_mm=(-200.0, -700.0, -250.0),
        envelope_max_mm=(950.0, 700.0, 900.0),
        max_tcp_speed_mm_s=250.0,
        max_tcp_accel_mm_s2=1200.0,
        max_joint_speed_rad_s=1.05,
        max_joint_accel_rad_s2=3.0,
        home_joints_deg=(180.0, -90.0, 90.0, -90.0, -90.0, 0.0),
    )


@pytest.fixture
def fake():
    with FakeURController(fresh_host(), joints=FACING_X) as controller:
        yield controller


class TestURRobotContract(RobotContract):
    @pytest.fixture
    def robot(self, fake):
        return URRobot(robot_config(fake.host))

    @pytest.fixture
    def reachable_pose(self):
        return pose_from_xyz_rpy([450.0, 100.0, 400.0], [np.pi, 0.0, 0.3])


def test_pose_sent_in_metres_and_rotation_vector(fake) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        T = pose_from_xyz_rpy([420.0, -80.0, 350.0], [2.9, 0.2, -0.4])
        robot.move_linear(T, 40.0, 150.0)
        np.testing.assert_allclose(robot.tool_pose(), T, atol=1e-9)
    finally:
        robot.close()
    cmd, args = fake.snapshot()["moves"][-1]
    assert cmd == 3  # moveL in ur_rtde's register protocol
    np.testing.assert_allclose(args[:3], [0.420, -0.080, 0.350])
    np.testing.assert_allclose(Rotation.from_rotvec(args[3:6]).as_matrix(), T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(args[6:8], [0.040, 0.150])  # m/s, m/s^2


@pytest.mark.parametrize("speed,accel", [(251.0, 100.0), (50.0, 1201.0), (0.0, 100.0)])
def test_limits_refused_before_sending(fake, speed: float, accel: float) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        with pytest.raises(PlanningError, match="cell config"):
            robot.move_linear(robot.tool_pose(), speed, accel)  # sim.yaml: 250 mm/s, 1200 mm/s^2
    finally:
        robot.close()
    assert fake.snapshot()["moves"] == []


def test_protective_stop_is_a_device_fault() -> None:
    with FakeURController(fresh_host(), joints=FACING_X, protective_stop_on_move=True) as fake:
        robot = URRobot(robot_config(fake.host))
        robot.connect()
        try:
            target = robot.tool_pose()
            target[2, 3] -= 20.0
            with pytest.raises(DeviceFault, match="protective stop"):
                robot.move_linear(target, 50.0, 200.0)
            state = robot.state()
            assert state.protective_stop and not state.normal
        finally:
            robot.close()


def test_refused_connection_is_fast() -> None:
    robot = URRobot(robot_config(fresh_host()))
    t0 = time.monotonic()
    with pytest.raises(DeviceFault, match="connection refused"):
        robot.connect()
    assert time.monotonic() - t0 < 1.0


def test_silent_controller_times_out() -> None:
    host = fresh_host()
    listeners = []
    for port in (29999, 30003, 30004):  # accept connections, never answer
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
        s.listen(4)
        listeners.append(s)
    try:
        robot = URRobot(robot_config(host), connect_timeout_s=0.3)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="30004"):
            robot.connect()
        assert time.monotonic() - t0 < 1.5
    finally:
        for s in listeners:
            s.close()


def _run_in_child(scenario, *args) -> tuple[str, str, float]:
    """Run a fault scenario in a fresh process: ur_rtde objects left behind by a dead stream or a failed
    script start can crash a later client in the same process (seen: segfault in the next connect)."""
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=scenario, args=(child, *args))
    proc.start()
    try:
        assert parent.poll(25.0), "scenario did not finish"
        return parent.recv()
    finally:
        proc.join(5.0)
        if proc.is_alive():
            proc.kill()


def _script_never_starts(pipe, host: str) -> None:
    robot = URRobot(robot_config(host))
    t0 = time.monotonic()
    try:
        robot.connect()
        pipe.send(("none", "", time.monotonic() - t0))
    except Exception as exc:
        pipe.send((type(exc).__name__, str(exc), time.monotonic() - t0))


def _silence_mid_session(pipe, host: str) -> None:
    robot = URRobot(robot_config(host), stale_timeout_s=0.3)
    robot.connect()
    robot.tool_pose()
    pipe.send(("connected", "", 0.0))
    pipe.recv()  # the test silenced the fake
    t0 = time.monotonic()
    try:
        for _ in range(3):
            robot.tool_pose()
        pipe.send(("none", "", time.monotonic() - t0))
    except Exception as exc:
        pipe.send((type(exc).__name__, str(exc), time.monotonic() - t0))


def test_script_that_never_starts_is_a_device_fault() -> None:
    with FakeURController(fresh_host(), script_starts=False) as fake:
        kind, message, elapsed = _run_in_child(_script_never_starts, fake.host)
    assert kind == "DeviceFault" and "control script" in message
    assert elapsed < 8.0  # ur_rtde's own 5 s wait for runtime_state PLAYING


def test_stream_silence_mid_session_times_out(fake) -> None:
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_silence_mid_session, args=(child, fake.host))
    proc.start()
    try:
        assert parent.poll(15.0) and parent.recv()[0] == "connected"
        fake.silence()
        parent.send("go")
        assert parent.poll(10.0)
        kind, message, elapsed = parent.recv()
    finally:
        proc.join(3.0)
        if proc.is_alive():
            proc.kill()
    assert kind == "DeviceTimeout" and "RTDE" in message
    assert elapsed < 1.0  # stale_timeout_s = 0.3 s


def test_dashboard_power_and_brakes(fake) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        robot.power_off()
        robot.power_on()
    finally:
        robot.close()
    assert fake.snapshot()["dashboard"][-3:] == ["power off", "power on", "brake release"]
