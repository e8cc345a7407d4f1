"""Universal Robots arm through ur_rtde (RTDE receive + control interfaces and the dashboard server).

Poses: UR controllers speak metres and rotation vectors; the cell speaks mm and 4x4 ``T_B_T`` matrices.
Limits: every motion is checked against the configured envelope and speed/acceleration limits *before*
anything is sent. ur_rtde's connect has no timeout and its calls hold the GIL while they block, so the
driver probes the three ports (and the RTDE handshake) from Python with a timeout first.
"""

from __future__ import annotations

import socket
import struct
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config import RobotConfig
from cell.contracts import Envelope, RobotMode, RobotState
from cell.errors import DeviceFault, DeviceTimeout, PlanningError
from cell.geometry import pose_from_xyz_rotvec, pose_to_xyz_rotvec

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
UR_POWERED_MODES = {5: RobotMode.IDLE, 7: RobotMode.IDLE}  # UR robot_mode IDLE (brakes on), RUNNING
PROTECTIVE_STOP_BIT, EMERGENCY_STOP_BIT = 2, 7  # RTDE safety_status_bits
STOP_SETTLE_S = 0.25  # after a failed move, how long the data stream may take to show a stop


def _probe(host: str, port: int, timeout_s: float, device: str, rtde: bool = False) -> None:
    """Connect to host:port within ``timeout_s``; for RTDE also check the protocol-version handshake."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as s:
            if rtde:
                s.sendall(struct.pack(">HBH", 5, ord("V"), 2))
                reply = s.recv(4)
                if len(reply) < 4 or reply[2:3] != b"V":
                    raise DeviceFault(device, f"{host}:{port} does not speak RTDE (answered {reply!r})")
    except ConnectionRefusedError as exc:
        raise DeviceFault(
            device,
            f"connection refused by {host}:{port}; is the controller on, the IP right "
            "and remote control enabled?",
        ) from exc
    except TimeoutError as exc:
        raise DeviceTimeout(
            device,
            f"no answer from {host}:{port} within {timeout_s:g} s; check the "
            "network cable and the robot's IP address",
        ) from exc
    except OSError as exc:
        raise DeviceFault(device, f"cannot reach {host}:{port}: {exc}") from exc


class URRobot:
    """A UR5e (or any e-Series arm) behind the Robot contract."""

    def __init__(
        self, config: RobotConfig, *, connect_timeout_s: float = 3.0, stale_timeout_s: float = 0.5
    ) -> None:
        self.name = config.name
        self._config = config
        self._connect_timeout_s = connect_timeout_s
        self._stale_timeout_s = stale_timeout_s
        self._envelope = Envelope(tuple(config.envelope_min_mm), tuple(config.envelope_max_mm))
        self._receive: Any = None
        self._control: Any = None
        self._dashboard: Any = None
        self._last_stamp: tuple[float, float] | None = None  # (controller timestamp, monotonic time seen)

    @property
    def envelope(self) -> Envelope:
        return self._envelope

    # ----------------------------------------------------------------------------------------- link
    def connect(self) -> None:
        """Probe the ports, then open receive, dashboard and control (which uploads the control script)."""
        if self._control is not None:
            return
        host = self._config.host
        for port in (DASHBOARD_PORT, SCRIPT_PORT):
            _probe(host, port, self._connect_timeout_s, self.name)
        _probe(host, RTDE_PORT, self._connect_timeout_s, self.name, rtde=True)
        try:
            import dashboard_client
            import rtde_control
            import rtde_receive
        except ImportError as exc:
            raise DeviceFault(
                self.name, f"ur_rtde is not installed ({exc}); pip install ur-rtde==1.6.5"
            ) from exc
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(host)
            self._dashboard = dashboard_client.DashboardClient(host)
            self._dashboard.connect()
            self._control = rtde_control.RTDEControlInterface(host)
        except (
            RuntimeError
        ) as exc:  # ur_rtde raises RuntimeError for every failure, e.g. the script not starting
            self.close()
            raise DeviceFault(self.name, f"ur_rtde could not take control of {host}: {exc}") from exc
        self._last_stamp = None

    def close(self) -> None:
        for attr, method in (
            ("_control", "stopScript"),
            ("_control", "disconnect"),
            ("_receive", "disconnect"),
            ("_dashboard", "disconnect"),
        ):
            obj = getattr(self, attr)
            if obj is not None:
                try:
                    getattr(obj, method)()
                except RuntimeError:
                    pass  # the link may already be gone; closing must not fail
        self._control = self._receive = self._dashboard = None

    def _fresh(self) -> Any:
        """The receive interface, after checking that its data still flows (raises DeviceTimeout if not)."""
        r = self._receive
        if r is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        deadline = time.monotonic() + self._stale_timeout_s
        while True:
            if not r.isConnected():
                raise DeviceTimeout(self.name, "RTDE data stream lost; check the network and the controller")
            stamp = r.getTimestamp()
            if self._last_stamp is None or stamp != self._last_stamp[0]:
                self._last_stamp = (stamp, time.monotonic())
                return r
            if time.monotonic() > deadline:
                raise DeviceTimeout(self.name, f"RTDE data stream silent for {self._stale_timeout_s:g} s")
            time.sleep(0.002)

    # ----------------------------------------------------------------------------------------- state
    def state(self) -> RobotState:
        if self._receive is None:
            return RobotState(mode=RobotMode.DISCONNECTED)
        r = self._fresh()
        bits = int(r.getSafetyStatusBits())
        mode = UR_POWERED_MODES.get(int(r.getRobotMode()), RobotMode.POWER_OFF)
        running = int(r.getRuntimeState()) == 2  # PLAYING: the control script runs
        return RobotState(
            mode=mode,
            protective_stop=bool(bits >> PROTECTIVE_STOP_BIT & 1),
            emergency_stop=bool(bits >> EMERGENCY_STOP_BIT & 1),
            program_running=running,
        )

    def tool_pose(self) -> NDArray[np.float64]:
        """``T_B_T`` in mm from the controller's actual TCP pose (TCP offset zero on the pendant)."""
        p = np.asarray(self._fresh().getActualTCPPose(), dtype=np.float64)
        return pose_from_xyz_rotvec(p[:3] * 1000.0, p[3:])

    def joints(self) -> NDArray[np.float64]:
        return np.asarray(self._fresh().getActualQ(), dtype=np.float64)

    # ----------------------------------------------------------------------------------------- motion
    def _check_limit(self, value: float, limit: float, what: str, unit: str) -> None:
        if not 0 < value <= limit:
            raise PlanningError(
                f"{self.name}: {what} {value:g} {unit} outside (0, {limit:g}] set in the cell config"
            )

    def _after_motion(self, ok: bool, what: str) -> None:
        if ok:  # wait for two new data packages so that reads show the state after the motion
            self._fresh()
            self._fresh()
            return
        # The safety bits of the data stream can trail the failed command by a package or more: watch the
        # stream for a short while before calling it a refusal rather than a stop.
        deadline = time.monotonic() + STOP_SETTLE_S
        while True:
            state = self.state()
            if state.protective_stop or state.emergency_stop:
                kind = "protective stop" if state.protective_stop else "emergency stop"
                raise DeviceFault(
                    self.name,
                    f"{what} stopped by a {kind}; clear the cause, then unlock it on the "
                    "pendant (or unlock_protective_stop())",
                )
            if time.monotonic() > deadline:
                break
        raise DeviceFault(self.name, f"controller refused {what}; check the pendant for the reason")

    def _control_ready(self) -> Any:
        if self._control is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        if self.state().protective_stop:
            raise DeviceFault(self.name, "robot is in a protective stop; clear it before moving")
        return self._control

    def move_linear(self, T_B_T: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float) -> None:
        """moveL to ``T_B_T`` (mm); PlanningError before moving if outside the envelope or the limits."""
        T = np.asarray(T_B_T, dtype=np.float64)
        if not self._envelope.contains(T[:3, 3]):
            raise PlanningError(
                f"{self.name}: target {np.round(T[:3, 3], 1).tolist()} mm is outside the envelope "
                f"{self._envelope.min_mm}..{self._envelope.max_mm} mm"
            )
        self._check_limit(speed_mm_s, self._config.max_tcp_speed_mm_s, "TCP speed", "mm/s")
        self._check_limit(accel_mm_s2, self._config.max_tcp_accel_mm_s2, "TCP acceleration", "mm/s^2")
        pose = pose_to_xyz_rotvec(T)
        pose[:3] /= 1000.0
        ok = self._control_ready().moveL(pose.tolist(), speed_mm_s / 1000.0, accel_mm_s2 / 1000.0)
        self._after_motion(ok, "moveL")

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float) -> None:
        q = np.asarray(joints_rad, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise PlanningError(f"{self.name}: joint target must be 6 finite angles (rad), got {q!r}")
        self._check_limit(speed_rad_s, self._config.max_joint_speed_rad_s, "joint speed", "rad/s")
        self._check_limit(accel_rad_s2, self._config.max_joint_accel_rad_s2, "joint acceleration", "rad/s^2")
        ok = self._control_ready().moveJ(q.tolist(), speed_rad_s, accel_rad_s2)
        self._after_motion(ok, "moveJ")

    def stop(self) -> None:
        """Decelerate along the path (stopL at the configured acceleration)."""
        if self._control is not None:
            self._control.stopL(self._config.max_tcp_accel_mm_s2 / 1000.0)

    # ----------------------------------------------------------------------------------------- dashboard
    def _dash(self, method: str) -> str:
        if self._dashboard is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        return str(getattr(self._dashboard, method)())

    def power_on(self) -> None:
        """Power the arm and release its brakes (dashboard ``power on`` + ``brake release``)."""
        self._dash("powerOn")
        self._dash("brakeRelease")

    def power_off(self) -> None:
        self._dash("powerOff")

    def unlock_protective_stop(self) -> None:
        self._dash("unlockProtectiveStop")
