"""URRobot through the real ur_rtde client against the fake UR controller (fakes/ur_controller.py) on its own
127.0.N.M loopback address per test: the Robot contract, unit conversion, limits and fault cases."""

from __future__ import annotations

import itertools
import multiprocessing
import os
import socket
import time
from collections.abc import Callable
from multiprocessing import forkserver

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.config import RobotConfig
from cell.contracts import RobotMode, RobotState
from cell.errors import DeviceFault, DeviceTimeout, MotionStopped, PlanningError
from cell.geometry import pose_from_xyz_rpy
from drivers.ur_robot import URRobot
from fakes.ur_controller import FakeURController
from tests.contracts.robot_contract import RobotContract

pytestmark = pytest.mark.timeout(30)
FACING_X = (np.pi, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)  # flange in front of the base (+x)
_hosts = itertools.count(2)


def fresh_host() -> str:
    return f"127.0.{os.getpid() % 250 + 1}.{next(_hosts)}"


def robot_config(host: str, **options) -> RobotConfig:
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
        options={"power_on_at_connect": True, **options},
    )


@pytest.fixture(scope="module", autouse=True)
def fake_controller_server():
    """The fake controllers of this module are forked from one server process (fakes/ur_controller.py);
    stopped and reaped at the module's end, so that no server outlives the tests and the CPU time of the
    processes it forked counts as this process's children's."""
    yield
    forkserver._forkserver._stop()  # the standard library's own tests stop it so


@pytest.fixture
def fake():
    with FakeURController(fresh_host(), joints=FACING_X) as controller:
        yield controller


class TestURRobotContract(RobotContract):
    speed_mm_s = 200.0  # the fake moves in real time: keep the contract's moves short
    accel_mm_s2 = 1000.0
    joint_speed_rad_s = 1.0
    joint_accel_rad_s2 = 3.0

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
        robot.move_linear(T, 100.0, 800.0)
        reached = robot.tool_pose()  # the forward kinematics of the joints the fake's IK reached
        assert np.linalg.norm(reached[:3, 3] - T[:3, 3]) < 0.03
        np.testing.assert_allclose(reached[:3, :3], T[:3, :3], atol=1e-6)
    finally:
        robot.close()
    cmd, args = fake.snapshot()["moves"][-1]
    assert cmd == 3  # moveL in ur_rtde's register protocol
    np.testing.assert_allclose(args[:3], [0.420, -0.080, 0.350])
    np.testing.assert_allclose(Rotation.from_rotvec(args[3:6]).as_matrix(), T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(args[6:8], [0.100, 0.800])  # m/s, m/s^2


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
    with pytest.raises(DeviceFault, match="connection refused") as info:
        robot.connect()
    assert isinstance(
        info.value.__cause__, ConnectionRefusedError
    )  # the first refusal, no wait for a timeout


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
        with pytest.raises(DeviceTimeout, match=r"30004 within 0\.3 s"):  # the configured timeout
            robot.connect()
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
        # after ur_rtde's own 5 s wait for runtime_state PLAYING (a hang fails _run_in_child's 25 s poll)
        kind, message, _ = _run_in_child(_script_never_starts, fake.host)
    assert kind == "DeviceLibraryError" and "control script" in message  # a DeviceFault naming ur_rtde


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
        kind, message, _ = parent.recv()
    finally:
        proc.join(3.0)
        if proc.is_alive():
            proc.kill()
    assert kind == "DeviceTimeout" and "RTDE data stream silent for 0.3 s" in message  # stale_timeout_s


def test_dashboard_power_and_brakes(fake) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        robot.power_off()
        robot.power_on()
    finally:
        robot.close()
    assert fake.snapshot()["dashboard"][-3:] == ["power off", "power on", "brake release"]
    assert fake.snapshot()["robot_mode"] == 7


# ------------------------------------------------------------------------------------------ safety (issue 13)
def _state_when(robot: URRobot, seen: Callable[[RobotState], bool], timeout_s: float = 2.0) -> RobotState:
    """The robot's state once ``seen`` holds, or the last state read after ``timeout_s``: the fake's change
    reaches the client with the next RTDE packet, which a loaded machine may delay past any fixed sleep."""
    deadline = time.monotonic() + timeout_s
    state = robot.state()
    while not seen(state) and time.monotonic() < deadline:
        time.sleep(0.01)
        state = robot.state()
    return state


@pytest.mark.parametrize(
    "bits,flag,normal",
    [
        (1 | 1 << 4, "safeguard_stop", False),  # a guard, door or light curtain
        (1 << 9, "fault", False),
        (1 << 8, "violation", False),
        (1 << 7, "emergency_stop", False),
        (1 | 1 << 1, "reduced", True),  # reduced mode: motion allowed, slower
    ],
)
def test_every_safety_status_bit_is_read(fake, bits: int, flag: str, normal: bool) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        fake.set("safety_bits", bits)
        state = _state_when(robot, lambda st: getattr(st, flag))
        assert getattr(state, flag) and state.normal is normal
        if not normal:
            with pytest.raises(DeviceFault, match="not ready for motion"):
                robot.move_joint(robot.joints() + 0.01, 0.5, 1.0)
            assert fake.snapshot()["moves"] == []  # refused before anything was sent
    finally:
        robot.close()


def test_powered_off_arm_is_refused_at_connect_or_powered_step_by_step() -> None:
    with FakeURController(fresh_host(), joints=FACING_X, power_step_s=0.3) as fake:
        robot = URRobot(robot_config(fake.host, power_on_at_connect=False))
        with pytest.raises(DeviceFault, match="power_off.*power it on.*power_on_at_connect"):
            robot.connect()
        assert fake.snapshot()["scripts_received"] == 0  # nothing uploaded, nothing can move
        robot = URRobot(robot_config(fake.host))
        t0 = time.monotonic()
        robot.connect()  # power on -> IDLE (brakes on) -> brake release -> RUNNING, each waited for
        try:
            assert time.monotonic() - t0 >= 0.6
            assert robot.state().mode is RobotMode.IDLE and robot.state().normal
            log = fake.snapshot()["dashboard"]
            assert log.index("power on") < log.index("brake release")
        finally:
            robot.close()


def test_brakes_on_is_not_ready() -> None:
    with FakeURController(fresh_host(), joints=FACING_X, powered=True) as fake:
        robot = URRobot(robot_config(fake.host))
        robot.connect()
        try:
            fake.set("robot_mode", 5)  # IDLE: powered, brakes on
            state = _state_when(robot, lambda st: st.mode is RobotMode.BRAKES_ON)
            assert state.mode is RobotMode.BRAKES_ON and not state.normal
        finally:
            robot.close()


def test_remote_control_off_is_a_clear_error_before_anything_moves() -> None:
    with FakeURController(fresh_host(), joints=FACING_X, remote_control=False) as fake:
        robot = URRobot(robot_config(fake.host))
        with pytest.raises(DeviceFault, match="not in remote control.*Remote Control"):
            robot.connect()
        snap = fake.snapshot()
        assert snap["scripts_received"] == 0 and snap["moves"] == [] and snap["robot_mode"] == 3


def test_joint_move_leaving_the_envelope_is_refused_before_sending(fake) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        q = robot.joints()
        with pytest.raises(PlanningError, match="moveJ path leaves the envelope"):
            robot.move_joint(q + np.array([np.pi, 0, 0, 0, 0, 0]), 0.5, 1.0)  # swings behind the base
        assert fake.snapshot()["moves"] == []
    finally:
        robot.close()


def test_streams_at_500_hz_and_moves_take_their_time(fake) -> None:
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        target = robot.tool_pose()
        target[2, 3] -= 50.0
        t0 = time.monotonic()
        robot.move_linear(target, 100.0, 1000.0)
        assert time.monotonic() - t0 >= 0.6  # 50 mm at 100 mm/s, 1000 mm/s^2: 0.6 s
        assert np.linalg.norm(robot.tool_pose()[:3, 3] - target[:3, 3]) < 0.03
    finally:
        robot.close()
    assert fake.snapshot()["frequencies"] and set(fake.snapshot()["frequencies"]) == {500.0}


def test_stop_from_another_thread_ends_the_move_mid_path(fake) -> None:
    import threading

    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        start = robot.tool_pose()
        target = start.copy()
        target[2, 3] -= 200.0  # 2 s at 100 mm/s
        timer = threading.Timer(0.5, robot.stop)
        timer.start()
        with pytest.raises(MotionStopped, match="into the move on request"):
            robot.move_linear(target, 100.0, 1000.0)
        time.sleep(0.1)
        travelled = start[2, 3] - robot.tool_pose()[2, 3]
        assert 20.0 < travelled < 120.0  # stopped mid-path (0.5 s in, plus the ramp), far from 200 mm
        assert 33 in fake.snapshot()["commands"]  # stopL
        assert robot.state().normal  # a stop on request latches nothing
        robot.move_linear(start, 200.0, 1000.0)
    finally:
        robot.close()


def test_protective_stop_ends_the_script_unlock_waits_then_reuploads() -> None:
    with FakeURController(
        fresh_host(), joints=FACING_X, protective_stop_on_move=True, unlock_delay_s=1.0
    ) as fake:
        robot = URRobot(robot_config(fake.host, unlock_wait_s=3.0))
        robot.connect()
        try:
            target = robot.tool_pose()
            target[2, 3] -= 40.0
            with pytest.raises(DeviceFault, match="protective stop"):
                robot.move_linear(target, 100.0, 1000.0)
            t_stop = time.monotonic()
            state = robot.state()
            assert state.protective_stop and not state.program_running
            robot.unlock_protective_stop()
            assert time.monotonic() - t_stop >= 0.8  # refused until 1 s after the stop
            snap = fake.snapshot()
            assert snap["dashboard"].count("unlock protective stop") >= 2
            assert snap["scripts_received"] == 2 and snap["runtime_state"] == 2  # uploaded again
            assert robot.state().normal
        finally:
            robot.close()


# Known flake under load, not a driver fault: on the 2-core machine running the whole suite, ur_rtde once
# reported the move after the re-upload as not accepted ("controller refused moveL", 26 Nov) while alone it
# passes every time; the fake's RTDE thread answers late when the CPU is saturated. Run again up to twice; a
# real double retry or lost move fails all three runs.
@pytest.mark.flaky(reruns=2, reruns_delay=1)
def test_a_stopped_script_is_uploaded_again_once_and_the_move_sent_once(fake) -> None:
    """No double retry: when the control script has ended (a stop on the pendant, a watchdog trip), the next
    move uploads it once and sends the move once; the driver does not retry on top of that."""
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        fake.set("runtime_state", 1)  # the program stopped between two moves
        _state_when(robot, lambda st: not st.program_running)
        target = robot.tool_pose()
        target[2, 3] -= 10.0
        robot.move_linear(target, 100.0, 1000.0)
        snap = fake.snapshot()
        assert snap["scripts_received"] == 2 and len(snap["moves"]) == 1
        robot.move_linear(robot.tool_pose(), 100.0, 1000.0)  # running again: no further upload
        assert fake.snapshot()["scripts_received"] == 2
    finally:
        robot.close()


def _move_until_killed(pipe, host: str) -> None:
    robot = URRobot(robot_config(host))
    robot.connect()
    target = robot.tool_pose()
    target[2, 3] -= 200.0
    pipe.send("moving")
    robot.move_linear(target, 100.0, 1000.0)  # 2 s; the test kills this process half way


def test_watchdog_stops_the_arm_when_the_controlling_process_dies(fake) -> None:
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_move_until_killed, args=(child, fake.host))
    proc.start()
    try:
        assert parent.poll(25.0) and parent.recv() == "moving"
        time.sleep(0.6)
        z_killed = fake.snapshot()["tcp"][2]
        proc.kill()  # SIGKILL: no handler, no stopL from the driver
        proc.join(5.0)
        deadline = time.monotonic() + 3.0  # 100 ms period + the ramp (0.1 m/s at 3 m/s^2: 33 ms) + load
        while time.monotonic() < deadline:
            snap = fake.snapshot()
            if not snap["moving"]:
                break
            time.sleep(0.05)
        assert any("watchdog" in e for e in snap["events"])
        assert not snap["moving"] and snap["runtime_state"] == 1
        travelled_mm = (z_killed - snap["tcp"][2]) * 1000.0
        assert (
            0.0 < travelled_mm < 60.0
        )  # stopped, ~0.15 s after the kill at 100 mm/s; the move had 120 mm left
    finally:
        if proc.is_alive():
            proc.kill()


def _second_controller(pipe, host: str) -> None:
    robot = URRobot(robot_config(host))
    try:
        robot.connect()
        pipe.send(("none", "", 0.0))
    except Exception as exc:
        pipe.send((type(exc).__name__, str(exc), 0.0))


def test_a_second_controller_on_the_same_arm_is_refused(fake) -> None:
    """The controller answers IN_USE for input registers another RTDE connection writes: a second process
    cannot take over an arm that one process controls, and the first keeps it."""
    robot = URRobot(robot_config(fake.host))
    robot.connect()
    try:
        kind, message, _ = _run_in_child(_second_controller, fake.host)
        assert kind == "DeviceLibraryError" and "already in use" in message and "another process" in message
        assert robot.state().normal
        target = robot.tool_pose()
        target[2, 3] -= 10.0
        robot.move_linear(target, 100.0, 1000.0)
    finally:
        robot.close()
