"""Universal Robots arm through ur_rtde (RTDE receive + control interfaces and the dashboard server).

Poses: UR controllers speak metres and rotation vectors; the cell speaks mm and 4x4 ``T_B_T`` matrices.
Limits: every motion is checked against the configured envelope and speed/acceleration limits *before*
anything is sent; a joint move's whole joint-space path is checked by forward kinematics. ur_rtde's connect
has no timeout and its calls hold the GIL while they block, so the driver probes the three ports (and the
RTDE handshake) from Python with a timeout first, and never sends a blocking move: moves are asynchronous
(``moveL(..., asynchronous=True)``) and polled every few ms, so :meth:`URRobot.stop` (from a signal handler
or another thread) ends one with stopL/stopJ within one poll. A watchdog (``setWatchdog``, kicked by a
thread of this process) stops the program and the arm when this process dies. Every ur_rtde RuntimeError
becomes a DeviceLibraryError naming the robot (the run pauses instead of faulting).
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config import RobotConfig
from cell.contracts import Envelope, RobotMode, RobotState
from cell.errors import DeviceFault, DeviceLibraryError, DeviceTimeout, MotionStopped, PlanningError
from cell.geometry import pose_from_xyz_rotvec, pose_to_xyz_rotvec
from cell.planning.kinematics import UR5E

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
# UR robot_mode -> contract mode. 7 RUNNING is powered with the brakes released; 5 IDLE has them ON.
UR_MODES = {
    -1: RobotMode.DISCONNECTED,
    0: RobotMode.DISCONNECTED,
    1: RobotMode.BOOTING,
    2: RobotMode.BOOTING,
    3: RobotMode.POWER_OFF,
    4: RobotMode.BRAKES_ON,
    5: RobotMode.BRAKES_ON,
    6: RobotMode.BRAKES_ON,
    7: RobotMode.IDLE,
    8: RobotMode.BOOTING,
}
# RTDE safety_status_bits (RTDE guide; ur_client_library UrRtdeSafetyStatusBits)
BIT_REDUCED, BIT_PROTECTIVE, BIT_RECOVERY, BIT_SAFEGUARD = 1, 2, 3, 4
BIT_SYSTEM_ESTOP, BIT_ROBOT_ESTOP, BIT_ESTOP, BIT_VIOLATION, BIT_FAULT = 5, 6, 7, 8, 9
STOP_SETTLE_S = 0.25  # after a failed move, how long the data stream may take to show a stop
POLL_S = 0.004  # how often a move is polled (the data stream runs at 500 Hz)


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
    """A UR5e (or any e-Series arm) behind the Robot contract.

    ``robot.options``: ``watchdog_hz`` (default 10; 0 turns the watchdog off), ``power_on_at_connect``
    (default false: a powered-off arm or one with its brakes on is an error at connect naming what to do),
    ``power_timeout_s`` (30), ``unlock_wait_s`` (6: the controller refuses an unlock for 5 s after a
    protective stop)."""

    def __init__(
        self, config: RobotConfig, *, connect_timeout_s: float = 3.0, stale_timeout_s: float = 0.5
    ) -> None:
        self.name = config.name
        self._config = config
        self._connect_timeout_s = connect_timeout_s
        self._stale_timeout_s = stale_timeout_s
        self._envelope = Envelope(config.envelope_min_mm, config.envelope_max_mm)
        options = dict(config.options)
        self._watchdog_hz = float(options.get("watchdog_hz", 10.0))
        self._power_on_at_connect = bool(options.get("power_on_at_connect", False))
        self._power_timeout_s = float(options.get("power_timeout_s", 30.0))
        self._unlock_wait_s = float(options.get("unlock_wait_s", 6.0))
        self._receive: Any = None
        self._control: Any = None
        self._dashboard: Any = None
        self._last_stamp: tuple[float, float] | None = None  # (controller timestamp, monotonic time seen)
        self._io = threading.RLock()  # one ur_rtde call at a time (the watchdog thread shares the link)
        self._kicker: threading.Thread | None = None
        self._kicking = threading.Event()
        self._moving: str | None = None  # "L" or "J" while a move is polled
        self._stop_requested = False

    @property
    def envelope(self) -> Envelope:
        return self._envelope

    def _call(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        """One ur_rtde call under the link lock; its RuntimeError becomes a DeviceLibraryError."""
        try:
            with self._io:
                return fn(*args)
        except RuntimeError as exc:
            raise DeviceLibraryError(
                self.name, f"ur_rtde {what} failed: {exc}; check the pendant's log, then `cell resume`"
            ) from exc

    # ----------------------------------------------------------------------------------------- link
    def connect(self) -> None:
        """Probe the ports; check remote control and power (before anything can move); open receive,
        dashboard and control (which uploads the control script); arm the watchdog."""
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
            self._dashboard = dashboard_client.DashboardClient(host)
            self._dashboard.connect()
            if not self._dashboard.isInRemoteControl():
                raise DeviceFault(
                    self.name,
                    f"{host} is not in remote control: switch the pendant to Remote Control (top right "
                    "corner) before the cell can move the arm",
                )
            self._receive = rtde_receive.RTDEReceiveInterface(host)
            mode = UR_MODES.get(int(self._receive.getRobotMode()), RobotMode.POWER_OFF)
            if mode is not RobotMode.IDLE:
                if not self._power_on_at_connect:
                    raise DeviceFault(
                        self.name,
                        f"arm is {mode.value}: power it on and release the brakes on the pendant, or set "
                        "robot.options.power_on_at_connect: true in the cell config",
                    )
                self.power_on()
            self._control = rtde_control.RTDEControlInterface(host)
            if self._watchdog_hz > 0:
                self._control.setWatchdog(self._watchdog_hz)
        except RuntimeError as exc:  # ur_rtde raises RuntimeError for every failure (script not starting...)
            self.close()
            hint = ""
            if "in use" in str(exc):  # the controller answered IN_USE for the input registers
                hint = "; another process (a second cell, a PLC adapter) writes this robot's input registers"
            raise DeviceLibraryError(
                self.name, f"ur_rtde could not take control of {host}: {exc}{hint}"
            ) from exc
        except BaseException:
            self.close()
            raise
        self._last_stamp = None
        if self._watchdog_hz > 0:
            self._kicking.set()
            self._kicker = threading.Thread(target=self._kick_loop, name=f"{self.name}-watchdog", daemon=True)
            self._kicker.start()

    def _kick_loop(self) -> None:
        """Kick the controller's watchdog at 4x its minimum rate while this process lives."""
        period = 0.25 / self._watchdog_hz
        while self._kicking.is_set():
            try:
                with self._io:
                    if self._control is not None:
                        self._control.kickWatchdog()
            except RuntimeError:
                pass  # the link is down: the next command reports it
            time.sleep(period)

    def close(self) -> None:
        self._kicking.clear()
        if self._kicker is not None:
            self._kicker.join(timeout=1.0)
            self._kicker = None
        for attr, method in (
            ("_control", "stopScript"),
            ("_control", "disconnect"),
            ("_receive", "disconnect"),
            ("_dashboard", "disconnect"),
        ):
            obj = getattr(self, attr)
            if obj is not None:
                try:
                    with self._io:
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
        """Every safety status bit and the robot mode from the data stream."""
        if self._receive is None:
            return RobotState(mode=RobotMode.DISCONNECTED)
        r = self._fresh()
        bits = int(r.getSafetyStatusBits())
        mode = UR_MODES.get(int(r.getRobotMode()), RobotMode.POWER_OFF)
        running = int(r.getRuntimeState()) == 2  # PLAYING: the control script runs

        def bit(n: int) -> bool:
            return bool(bits >> n & 1)

        return RobotState(
            mode=mode,
            protective_stop=bit(BIT_PROTECTIVE),
            emergency_stop=bit(BIT_ESTOP) or bit(BIT_SYSTEM_ESTOP) or bit(BIT_ROBOT_ESTOP),
            program_running=running,
            safeguard_stop=bit(BIT_SAFEGUARD),
            fault=bit(BIT_FAULT),
            violation=bit(BIT_VIOLATION) or bit(BIT_RECOVERY),
            reduced=bit(BIT_REDUCED),
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

    def _raise_stop(self, what: str) -> None:
        """After a failed or interrupted move: watch the stream briefly for the stop that caused it (the bits
        can trail the command) and raise what it was."""
        deadline = time.monotonic() + STOP_SETTLE_S
        while True:
            state = self.state()
            if not state.normal:
                raise DeviceFault(
                    self.name,
                    f"{what} stopped by {state.why_not_normal}; clear the cause, then unlock it on the "
                    "pendant (or unlock_protective_stop()) and `cell resume`",
                )
            if time.monotonic() > deadline:
                break
        if not state.program_running:
            raise DeviceFault(
                self.name,
                f"the control script ended during {what} (a runtime error, e.g. out of reach, or "
                "the watchdog); see the pendant's log",
            )
        raise DeviceFault(self.name, f"controller refused {what}; check the pendant for the reason")

    def _control_ready(self) -> Any:
        """The control interface, with the robot normal and the control script running: a script ended by
        a protective stop or a watchdog trip is uploaded again once (not on every call: ur_rtde also
        reconnects by itself, and two recoveries on top of each other would fight)."""
        if self._control is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        state = self.state()
        if not state.normal:
            raise DeviceFault(self.name, f"not ready for motion: {state.why_not_normal}")
        if not state.program_running:
            self._reupload()
        return self._control

    def _reupload(self) -> None:
        """Upload the control script again (a protective stop or a watchdog trip ended it), wait until it
        runs, and arm the watchdog again (the controller removes watchdogs when a program stops)."""
        self._call("reuploadScript", self._control.reuploadScript)
        deadline = time.monotonic() + 3.0
        while not self.state().program_running:
            if time.monotonic() > deadline:
                raise DeviceFault(
                    self.name, "the control script does not run after a re-upload; see the pendant"
                )
            time.sleep(0.01)
        if self._watchdog_hz > 0:
            self._call("setWatchdog", self._control.setWatchdog, self._watchdog_hz)

    def _run(self, what: str, kind: str, send: Callable[[Any], bool]) -> None:
        """Send an asynchronous move and poll it until it ends, a stop is requested or the arm stops."""
        control = self._control_ready()
        op_before = self._call(
            "getAsyncOperationProgressEx", control.getAsyncOperationProgressEx
        ).operationId()
        if self._stop_requested:
            raise MotionStopped(self.name, f"{what} not sent: a stop was requested")
        self._moving = kind
        try:
            if not self._call(what, send, control):
                self._raise_stop(what)
            t0 = time.monotonic()
            while True:
                if self._stop_requested:
                    elapsed = time.monotonic() - t0
                    self._stop_now(kind)
                    raise MotionStopped(self.name, f"{what} stopped {elapsed:.3f} s into the move on request")
                status = self._call("getAsyncOperationProgressEx", control.getAsyncOperationProgressEx)
                if status.operationId() != op_before and not status.isAsyncOperationRunning():
                    break
                state = self.state()
                if not (state.normal and state.program_running):
                    self._raise_stop(what)
                time.sleep(POLL_S)
        finally:
            self._moving = None
        self._fresh()  # two new data packages: reads show the state after the motion
        self._fresh()
        state = self.state()
        if not state.normal:
            self._raise_stop(what)

    def _stop_now(self, kind: str) -> None:
        """stopL/stopJ at the configured acceleration, sent asynchronously, then wait for the ramp."""
        if self._control is None:
            return
        if kind == "J":
            self._call("stopJ", self._control.stopJ, self._config.max_joint_accel_rad_s2, True)
        else:
            self._call("stopL", self._control.stopL, self._config.max_tcp_accel_mm_s2 / 1000.0, True)
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            status = self._call("getAsyncOperationProgressEx", self._control.getAsyncOperationProgressEx)
            if not status.isAsyncOperationRunning():
                return
            time.sleep(POLL_S)

    def move_linear(self, T_B_T: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float) -> None:
        """moveL to ``T_B_T`` (mm); PlanningError before moving if outside the envelope or the limits."""
        self._stop_requested = False
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
        v, a = speed_mm_s / 1000.0, accel_mm_s2 / 1000.0
        self._run("moveL", "L", lambda c: c.moveL(pose.tolist(), v, a, True))

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float) -> None:
        """moveJ to ``joints_rad``; PlanningError before moving if a joint leaves its limits or the flange
        leaves the envelope anywhere on the joint-space path (forward kinematics every 0.5 deg)."""
        self._stop_requested = False
        q = np.asarray(joints_rad, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise PlanningError(f"{self.name}: joint target must be 6 finite angles (rad), got {q!r}")
        self._check_limit(speed_rad_s, self._config.max_joint_speed_rad_s, "joint speed", "rad/s")
        self._check_limit(accel_rad_s2, self._config.max_joint_accel_rad_s2, "joint acceleration", "rad/s^2")
        lo, hi = np.asarray(UR5E.joint_min_rad), np.asarray(UR5E.joint_max_rad)
        if np.any(q < lo) or np.any(q > hi):
            j = int(np.argmax((q < lo) | (q > hi)))
            raise PlanningError(
                f"{self.name}: joint {j + 1} target {q[j]:.4f} rad outside [{lo[j]:.4f}, {hi[j]:.4f}]"
            )
        q0 = self.joints()
        n = max(int(np.ceil(np.max(np.abs(q - q0)) / np.radians(0.5))), 1) + 1
        path = q0 + np.linspace(0.0, 1.0, n)[:, None] * (q - q0)
        flange = UR5E.fk(path)[:, :3, 3]
        inside = np.all(
            (flange >= np.asarray(self._envelope.min_mm)) & (flange <= np.asarray(self._envelope.max_mm)),
            axis=1,
        )
        if not inside.all():
            p = flange[np.argmin(inside)]
            raise PlanningError(
                f"{self.name}: moveJ path leaves the envelope at flange {np.round(p, 1).tolist()} mm "
                f"(envelope {self._envelope.min_mm}..{self._envelope.max_mm} mm)"
            )
        self._run("moveJ", "J", lambda c: c.moveJ(q.tolist(), speed_rad_s, accel_rad_s2, True))

    def stop(self) -> None:
        """Stop any motion now. Safe from a signal handler or another thread: during a move it only sets a
        flag that the polling loop turns into stopL/stopJ within one poll (a few ms); otherwise it sends
        stopL itself."""
        self._stop_requested = True
        if self._moving is not None or self._control is None:
            return
        try:
            self._stop_now("L")
        except DeviceLibraryError:
            pass  # no program to stop: nothing moves

    # ----------------------------------------------------------------------------------------- dashboard
    def _dash(self, method: str) -> str:
        if self._dashboard is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        return str(self._call(method, getattr(self._dashboard, method)))

    def _wait_mode(self, wanted: set[int], what: str) -> None:
        deadline = time.monotonic() + self._power_timeout_s
        while True:
            mode = int(self._fresh().getRobotMode())
            if mode in wanted:
                return
            if time.monotonic() > deadline:
                raise DeviceTimeout(
                    self.name,
                    f"{what}: robot mode still {mode} after {self._power_timeout_s:g} s; see the pendant",
                )
            time.sleep(0.02)

    def power_on(self) -> None:
        """Power the arm (wait for IDLE, brakes on) and release its brakes (wait for RUNNING)."""
        self._dash("powerOn")
        self._wait_mode({5, 7}, "power on")
        self._dash("brakeRelease")
        self._wait_mode({7}, "brake release")

    def power_off(self) -> None:
        self._dash("powerOff")

    def unlock_protective_stop(self) -> None:
        """Unlock a protective stop: the controller refuses for 5 s after it, so retry until
        ``unlock_wait_s``; then upload the control script again (the stop ended it)."""
        if self._dashboard is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        deadline = time.monotonic() + self._unlock_wait_s
        while True:
            try:
                with self._io:
                    self._dashboard.unlockProtectiveStop()
                refusal = ""
            except RuntimeError as exc:  # "Cannot unlock protective stop until 5s after occurrence..."
                refusal = str(exc)
            time.sleep(0.05)
            self._fresh()
            if not self.state().protective_stop:
                break
            if time.monotonic() > deadline:
                raise DeviceFault(
                    self.name,
                    f"protective stop not unlocked within {self._unlock_wait_s:g} s "
                    f"({refusal or 'no reason given'}); see the pendant",
                )
            time.sleep(0.25)
        if self._control is not None and not self.state().program_running:
            self._reupload()
