"""A fake Universal Robots controller on 127.0.0.N that the real ur_rtde client talks to.

It serves the three ports ur_rtde uses, per the public RTDE guide and the dashboard server manual:

* RTDE (30004): uint16 size + uint8 type header, big-endian; V (protocol version), v (controller version),
  O (output recipe), I (input recipes, numbered 1, 2, 3... per connection in arrival order), S/P (start,
  pause), U (data packages, sent every ``period_s`` after S; the client gives up after ~2.5 s of silence).
* Dashboard (29999): a greeting line, then one reply line per command line.
* Script (30003): receives the control script; the "script" then runs when ``script_starts``: runtime_state
  becomes PLAYING and output_int_register_0 = 1 (ready).

Motion follows ur_rtde's register handshake (the control script ur_rtde 1.6.5 uploads): the client writes
input_int_register_0 (1 = moveJ, 3 = moveL, 33 = stopL, 34 = stopJ, 35 = set watchdog, 255 = stop script)
with targets in input_double_register_0..5, speed/acceleration in 6..7 and input_int_register_1 = 1 for an
asynchronous move; the fake answers output_int_register_0 = 2 (done with the command; for an async move at
once, for a sync move when the arm arrives) and goes back to 1 when the client clears the command (0).
Asynchronous moves report in output_int_register_2 as the script does (bit 15 running, bits 16-22 a write
counter, bits 24-30 the operation id).

As strict as the real controller where the tests need it:
* Motion takes its time: moveJ is a joint trapezoid (the leading joint at v, a); moveL a straight line with
  slerped orientation on a trapezoid of its length, the joints following by inverse kinematics (the fake's
  own damped Gauss-Newton on its own DH forward kinematics) every cycle: the reported pose is the forward
  kinematics of those joints, never the commanded pose. A moveL whose path leaves the reach ends the script
  (as the controller's "inverse kinematics failed" runtime error does).
* stopL/stopJ decelerate from the present speed at the given rate; a protective stop
  (``protective_stop_on_move``: half way through the next move) halts the arm and ends the script, and
  ``unlock protective stop`` is refused for ``unlock_delay_s`` (5 s on a real controller) after it; the
  script must then be uploaded again.
* The watchdog (``rtde_set_watchdog("input_int_register_0", f, "stop")``) stops the program and the arm when
  no input package with that register arrives for 1/f s; it is removed when the program stops.
* The arm starts powered off (``robot_mode`` 3) unless ``powered=True``; ``power on`` goes through POWER_ON
  (4) to IDLE (5, brakes on) and ``brake release`` to RUNNING (7), each taking ``power_step_s``; the script
  runs only in RUNNING. With ``remote_control=False`` the dashboard refuses control commands and the
  controller ignores uploaded scripts.
* Input registers claimed by one RTDE connection answer IN_USE to another (two controllers on one arm).
* Data packages stream at the frequency the client asks for in its output setup (500 Hz for ur_rtde on an
  e-Series controller).
Port 30003 only receives the script: ur_rtde 1.6.5 reads no state from it. Fault cases also
``script_starts=False`` and :meth:`silence`; a refused connection is simply no fake on that address.
"""

from __future__ import annotations

import math
import multiprocessing
import re
import select
import socket
import struct
import threading
import time
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
MOTION_CYCLE_S = 0.008  # the fake updates the arm at 125 Hz (IK in Python); it streams at up to 500 Hz
CONTROLLER_VERSION = (5, 11, 1, 108318)  # e-Series: the client then asks for 500 Hz
POLYSCOPE = "URSoftware 5.11.1.108318 (Feb 04 2022)"

# RTDE type name -> struct format (big-endian when packed)
TYPE_FORMATS = {
    "DOUBLE": "d",
    "UINT64": "Q",
    "UINT32": "I",
    "INT32": "i",
    "UINT8": "B",
    "BOOL": "?",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_VEC6 = (
    "target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
    "joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed "
    "joint_temperatures actual_joint_voltage ft_raw_wrench actual_current_window actual_current_as_torque "
    "tcp_offset target_current_window joint_position_deviation_ratio external_force_torque"
).split()
_VEC3 = "actual_tool_accelerometer payload_cog elbow_position elbow_velocity payload_inertia".split()
_DOUBLE = (
    "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum "
    "actual_main_voltage actual_robot_voltage actual_robot_current standard_analog_input0 "
    "standard_analog_input1 standard_analog_output0 standard_analog_output1 payload tool_analog_input0 "
    "tool_analog_input1 tool_output_current tool_temperature io_current speed_slider_fraction "
    "standard_analog_output_0 standard_analog_output_1 euromap67_24V_voltage euromap67_24V_current "
    "tool_output_voltage_double"
).split()
_INT32 = "robot_mode safety_mode safety_status tool_output_voltage".split()
_UINT32 = (
    "runtime_state robot_status_bits safety_status_bits tool_mode script_control_line speed_slider_mask "
    "input_bit_registers0_to_31 input_bit_registers32_to_63 output_bit_registers0_to_31 "
    "output_bit_registers32_to_63"
).split()
_UINT64 = (
    "actual_digital_input_bits actual_digital_output_bits euromap67_input_bits euromap67_output_bits"
).split()
_UINT8 = (
    "analog_io_types tool_analog_input_types tool_output_mode tool_digital_output0_mode "
    "tool_digital_output1_mode standard_digital_output_mask standard_digital_output "
    "configurable_digital_output_mask configurable_digital_output tool_digital_output_mask "
    "tool_digital_output standard_analog_output_mask standard_analog_output_type"
).split()
TYPES: dict[str, str] = {
    **{n: "VECTOR6D" for n in _VEC6},
    **{n: "VECTOR3D" for n in _VEC3},
    **{n: "DOUBLE" for n in _DOUBLE},
    **{n: "INT32" for n in _INT32},
    **{n: "UINT32" for n in _UINT32},
    **{n: "UINT64" for n in _UINT64},
    **{n: "UINT8" for n in _UINT8},
    "joint_mode": "VECTOR6INT32",
}
_REGISTER = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)$")


def rtde_type(name: str) -> str | None:
    """The RTDE type of a variable, or None (the controller answers NOT_FOUND)."""
    m = _REGISTER.match(name)
    if m:
        return {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}[m.group(2)]
    return TYPES.get(name)


# UR5e standard DH parameters (Universal Robots, "DH parameters for calculations of kinematics"), metres
UR5E_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
UR5E_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
UR5E_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)


def _forward_batch(q: np.ndarray) -> np.ndarray:
    """Flange matrices (n, 4, 4) of joint rows q (n, 6), standard DH (metres)."""
    q = np.atleast_2d(q)
    T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    for j, (d, a, al) in enumerate(zip(UR5E_D, UR5E_A, UR5E_ALPHA)):
        ct, st = np.cos(q[:, j]), np.sin(q[:, j])
        ca, sa = math.cos(al), math.sin(al)
        L = np.zeros((len(q), 4, 4))
        L[:, 0, 0], L[:, 0, 1], L[:, 0, 2], L[:, 0, 3] = ct, -st * ca, st * sa, a * ct
        L[:, 1, 0], L[:, 1, 1], L[:, 1, 2], L[:, 1, 3] = st, ct * ca, -ct * sa, a * st
        L[:, 2, 1], L[:, 2, 2], L[:, 2, 3], L[:, 3, 3] = sa, ca, d, 1.0
        T = T @ L
    return T


def _forward_matrix(q: np.ndarray) -> np.ndarray:
    return _forward_batch(np.asarray(q, dtype=np.float64))[0]


def ur5e_forward(q: np.ndarray) -> np.ndarray:
    """Flange pose [x, y, z (m), rx, ry, rz (rotvec)] of a UR5e at joints q (rad), standard DH."""
    T = _forward_matrix(q)
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def ur5e_inverse(T_goal: np.ndarray, q0: np.ndarray, iterations: int = 8) -> tuple[np.ndarray, float]:
    """Joints near ``q0`` whose flange is at ``T_goal`` (4x4, m): Gauss-Newton with a numerical Jacobian
    on :func:`_forward_batch` (written here rather than reusing the cell's closed-form IK: the peer must
    not share the model's code). Returns (q, residual in m + rad)."""
    q = np.array(q0, dtype=np.float64)
    h = 1e-7
    probes = np.vstack([np.zeros(6), h * np.eye(6)])

    def errors(qv: np.ndarray) -> np.ndarray:  # (7, 6): at qv and at qv + h e_j
        T = _forward_batch(qv + probes)
        R = np.einsum("ij,nkj->nik", T_goal[:3, :3], T[:, :3, :3])  # R_goal @ R^T
        rot = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
        return np.hstack([T_goal[:3, 3] - T[:, :3, 3], rot])

    for _ in range(iterations):
        e = errors(q)
        if np.linalg.norm(e[0]) < 1e-10:
            break
        J = (e[0] - e[1:]).T / h
        q = q + np.linalg.lstsq(J, e[0], rcond=None)[0]
    return q, float(np.linalg.norm(errors(q)[0]))


def _pose_matrix(p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(p[3:6]).as_matrix()
    T[:3, 3] = p[:3]
    return T


def _trapezoid(t: float, d: float, v: float, a: float) -> tuple[float, float, float]:
    """(position, speed, duration) of a rest-to-rest trapezoid over ``d`` at ``t``."""
    if d <= 0.0:
        return 0.0, 0.0, 0.0
    if d >= v * v / a:
        ta, T = v / a, d / v + v / a
    else:
        ta = math.sqrt(d / a)
        T, v = 2 * ta, a * ta
    t = min(max(t, 0.0), T)
    if t < ta:
        return 0.5 * a * t * t, a * t, T
    if t <= T - ta:
        return 0.5 * a * ta * ta + v * (t - ta), v, T
    r = T - t
    return d - 0.5 * a * r * r, a * r, T


class _Move:
    """One motion on the controller's clock: a path parameter s(t) on a trapezoid (or a stop ramp)."""

    def __init__(self, kind: int, q0: np.ndarray, target: list[float], v: float, a: float, t0: float):
        self.kind, self.t0, self.v, self.a = kind, t0, v, a
        self.q0 = q0.copy()
        if kind == 1:  # moveJ: joints straight in joint space, the leading joint sets the time
            self.qt = np.array(target[:6])
            self.d = float(np.max(np.abs(self.qt - q0)))
        else:  # moveL: the flange on a straight line, orientation slerped
            self.T0, self.T1 = _forward_matrix(q0), _pose_matrix(np.array(target[:6]))
            self.rots = Rotation.from_matrix(np.stack([self.T0[:3, :3], self.T1[:3, :3]]))
            self.d = float(np.linalg.norm(self.T1[:3, 3] - self.T0[:3, 3]))
            if self.d < 1e-6:  # a pure rotation: timed on the angle (v, a read as rad/s, rad/s^2)
                self.d = float(np.linalg.norm((self.rots[0].inv() * self.rots[1]).as_rotvec()))
        self.duration = _trapezoid(0.0, self.d, v, a)[2]
        self.stop: tuple[float, float, float, float] | None = None  # (t, s, speed, decel)

    def s_at(self, t: float) -> float:
        if self.stop is not None and t >= self.stop[0]:
            ts, s0, v0, dec = self.stop
            dt = min(t - ts, v0 / dec if dec > 0 else 0.0)
            return min(s0 + v0 * dt - 0.5 * dec * dt * dt, self.d)
        return _trapezoid(t, self.d, self.v, self.a)[0]

    def end_t(self) -> float:
        if self.stop is None:
            return self.duration
        ts, _, v0, dec = self.stop
        return ts + (v0 / dec if dec > 0 else 0.0)

    def begin_stop(self, t: float, decel: float) -> None:
        if self.stop is None and t < self.duration:
            s, v, _ = _trapezoid(t, self.d, self.v, self.a)
            self.stop = (t, s, v, max(decel, 1e-9))

    def pose_at(self, s: float) -> np.ndarray:
        """The 4x4 flange goal (moveL) at path parameter s."""
        u = 0.0 if self.d <= 0 else s / self.d
        from scipy.spatial.transform import Slerp

        T = np.eye(4)
        T[:3, :3] = Slerp([0.0, 1.0], self.rots)([min(max(u, 0.0), 1.0)]).as_matrix()[0]
        if np.linalg.norm(self.T1[:3, 3] - self.T0[:3, 3]) >= 1e-6:
            T[:3, 3] = self.T0[:3, 3] + u * (self.T1[:3, 3] - self.T0[:3, 3])
        else:
            T[:3, 3] = self.T0[:3, 3]
        return T


class ControllerServer:
    """The three servers on ``host``, state shared by all connections. Runs in its own process
    (:class:`FakeURController`): ur_rtde's client holds the GIL while it blocks, so threads in the test
    process could not answer it."""

    def __init__(
        self,
        host: str,
        *,
        script_starts: bool = True,
        protective_stop_on_move: bool = False,
        period_s: float = 0.008,
        joints: tuple[float, ...] = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0),
        powered: bool = False,
        remote_control: bool = True,
        unlock_delay_s: float = 5.0,
        power_step_s: float = 0.2,
        program_stop_decel: float = 3.0,
    ) -> None:
        self.host = host
        self.script_starts = script_starts
        self.protective_stop_on_move = protective_stop_on_move
        self.period_s = period_s  # until the client asks for its frequency
        self.remote_control = remote_control
        self.unlock_delay_s = unlock_delay_s
        self.power_step_s = power_step_s
        self.program_stop_decel = program_stop_decel  # m/s^2 or rad/s^2 when the program stops mid-move
        self.q = np.array(joints, dtype=np.float64)
        self.tcp = ur5e_forward(self.q)
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.inputs: dict[str, Any] = {}
        self.robot_mode = 7 if powered else 3  # 3 POWER_OFF, 4 POWER_ON, 5 IDLE (brakes on), 7 RUNNING
        self.safety_bits = 1  # bit 0: normal mode; bit 2: protective stop; bit 4: safeguard stop
        self.runtime_state = 1  # STOPPED; 2 = PLAYING
        self.moves: list[tuple[int, list[float]]] = []  # (command, doubles 0..7) as received
        self.commands: list[int] = []  # every command number received, in order
        self.dashboard_log: list[str] = []
        self.unknown_variables: set[str] = set()
        self.frequencies: list[float] = []  # what each output setup asked for (Hz)
        self.events: list[str] = []  # what the controller did on its own: trips, runtime errors
        self.scripts_received = 0
        self._move: _Move | None = None
        self._move_sync = False
        self._stop_sync = False
        self._protective_at: float | None = None
        self._mode_pending: tuple[float, int] | None = None
        self._watchdog_s: float | None = None
        self._watch_silence = 0.0  # s of the fake's cycles without input_int_register_0
        self._async_wr = self._async_op = 0
        self._input_owner: dict[str, int] = {}
        self._protective_times: list[float] = []
        self._last_advance = 0.0
        self._silent = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._listeners: list[socket.socket] = []
        self._threads: list[threading.Thread] = []

    # --------------------------------------------------------------------------------------- lifecycle
    def snapshot(self) -> dict[str, Any]:
        """What a test may check: received moves and dashboard commands, joints and flange pose."""
        with self._lock:
            return {
                "moves": list(self.moves),
                "commands": list(self.commands),
                "dashboard": list(self.dashboard_log),
                "q": self.q.copy(),
                "tcp": self.tcp.copy(),
                "unknown_variables": set(self.unknown_variables),
                "robot_mode": self.robot_mode,
                "safety_bits": self.safety_bits,
                "runtime_state": self.runtime_state,
                "moving": self._move is not None,
                "frequencies": list(self.frequencies),
                "events": list(self.events),
                "scripts_received": self.scripts_received,
            }

    def set(self, name: str, value: Any) -> None:
        """Change a state variable from the test (e.g. safety_bits to open a guard)."""
        with self._lock:
            setattr(self, name, value)
            if name == "safety_bits" and value & 0b10000 and self._move is not None:
                self._move.begin_stop(time.monotonic() - self._move.t0, self.program_stop_decel)

    def __enter__(self) -> ControllerServer:
        for port, handler in (
            (RTDE_PORT, self._rtde),
            (DASHBOARD_PORT, self._dashboard),
            (SCRIPT_PORT, self._script),
        ):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((self.host, port))
            s.listen(4)
            s.settimeout(0.05)
            self._listeners.append(s)
            self._spawn(self._accept, s, handler)
        self._spawn(self._cycle)
        return self

    def _cycle(self) -> None:
        """The controller's own clock: the arm moves and the watchdog counts with or without clients."""
        while not self._stop.is_set():
            with self._lock:
                self._advance()
            time.sleep(MOTION_CYCLE_S / 2)

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        for s in self._listeners:
            s.close()

    def _spawn(self, target: Any, *args: Any) -> None:
        t = threading.Thread(target=target, args=args, daemon=True)
        self._threads.append(t)
        t.start()

    def _accept(self, listener: socket.socket, handler: Any) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = listener.accept()
            except (TimeoutError, OSError):
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._spawn(self._serve, conn, handler)

    def _serve(self, conn: socket.socket, handler: Any) -> None:
        try:
            handler(conn)
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            with self._lock:  # a closed connection frees the input registers it claimed
                for name in [n for n, owner in self._input_owner.items() if owner == id(conn)]:
                    del self._input_owner[name]
            conn.close()

    def silence(self) -> None:
        """Stop sending RTDE data packages (sockets stay open), as a hung controller would."""
        self._silent.set()

    # --------------------------------------------------------------------------------------- state
    def _value(self, name: str) -> Any:
        m = _REGISTER.match(name)
        if m and m.group(1) == "output":
            idx = int(m.group(3))
            registers: dict[str, list[Any]] = {"int": self.out_int, "double": self.out_double}
            return registers.get(m.group(2), [False] * 128)[idx]
        if name in ("actual_q", "target_q"):
            return self.q
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return self.tcp
        return {
            "timestamp": time.monotonic() - self._t0,
            "robot_mode": self.robot_mode,
            "safety_mode": 3 if self.safety_bits & 4 else (5 if self.safety_bits & 16 else 1),
            "safety_status": 3 if self.safety_bits & 4 else (5 if self.safety_bits & 16 else 1),
            "safety_status_bits": self.safety_bits,
            "runtime_state": self.runtime_state,
            "robot_status_bits": (1 if self.robot_mode >= 4 else 0) | (2 if self.runtime_state == 2 else 0),
            "speed_scaling": 1.0,
            "target_speed_fraction": 1.0,
        }.get(name, 0)

    def _async_progress(self, running: bool, started: bool = False) -> None:
        """output_int_register_2 as the control script writes it (see the module docstring)."""
        self._async_wr = (self._async_wr + 1) % 128
        if started:
            self._async_op = (self._async_op + 1) % 128
        value = self._async_wr * 65536 + self._async_op * 16777216 + (32768 if running else 0)
        self.out_int[2] = value

    def _end_program(self, why: str) -> None:
        """The program stops (protective stop, watchdog, runtime error): the script's registers go quiet."""
        self.runtime_state, self.out_int[0] = 1, 0
        self._watchdog_s = None  # "all watchdogs are removed on program stop"
        self.events.append(why)

    def _on_input(self, values: dict[str, Any]) -> None:
        self.inputs.update(values)
        cmd = values.get("input_int_register_0")
        if cmd is None:
            return
        self._watch_silence = 0.0
        if cmd == 0 and self.out_int[0] == 2:
            self.out_int[0] = 1  # command cleared: ready for the next one
            return
        if not cmd or self.runtime_state != 2 or self.out_int[0] != 1:
            return
        cmd = int(cmd)
        self.commands.append(cmd)
        args = [float(self.inputs.get(f"input_double_register_{i}", 0.0)) for i in range(8)]
        asynchronous = int(self.inputs.get("input_int_register_1", 0)) == 1
        now = time.monotonic()
        if cmd == 255:
            self._end_program("script stopped by the client")
            return
        if cmd in (1, 3):
            self.moves.append((cmd, args))
            self.out_int[0] = 0  # busy
            self._start_move(cmd, args, asynchronous, now)
            return
        if cmd in (33, 34):  # stopL / stopJ at args[0]
            if self._move is not None:
                self._move.begin_stop(now - self._move.t0, args[0])
            if asynchronous or self._move is None:
                self.out_int[0] = 2
            else:
                self.out_int[0], self._stop_sync = 0, True
            return
        if cmd == 35:  # rtde_set_watchdog("input_int_register_0", args[0], "stop")
            self._watchdog_s = 1.0 / args[0] if args[0] > 0 else None
        self.out_int[0] = 2  # every other command: done at once

    def _start_move(self, cmd: int, args: list[float], asynchronous: bool, now: float) -> None:
        if self.safety_bits != 1 or self.robot_mode != 7:
            self._end_program("move refused: robot not in normal mode")
            return
        move = _Move(cmd, self.q, args, args[6], args[7], now)
        if cmd == 3:  # the controller checks the whole line for reach before it moves
            q = self.q.copy()
            for s in np.linspace(0.0, move.d, 21)[1:]:
                q, residual = ur5e_inverse(move.pose_at(s), q, iterations=12)
                if residual > 1e-7:
                    self._end_program("inverse kinematics failed: moveL target or path out of reach")
                    return
            move.t0 = now = time.monotonic()  # the check took the fake's time, not the arm's
            self._watch_silence = 0.0
        self._move, self._move_sync = move, not asynchronous
        self._protective_at = now + move.duration / 2 if self.protective_stop_on_move else None
        if asynchronous:
            self._async_progress(running=True, started=True)
            self.out_int[0] = 2

    def _advance(self) -> None:
        now = time.monotonic()
        if now - self._last_advance < MOTION_CYCLE_S:  # one motion update for all connections together
            return
        # Client silence is counted in the fake's own cycles, at most 2 per update: when the fake itself
        # stalls (a busy test machine), reading the client's inputs stalled too, and that is not the client's
        # silence. A real controller never stalls; this only makes a trip later, never earlier.
        self._watch_silence += min(now - self._last_advance, 2 * MOTION_CYCLE_S)
        self._last_advance = now
        if self._mode_pending and now >= self._mode_pending[0]:
            self.robot_mode = self._mode_pending[1]
            self._mode_pending = (now + self.power_step_s, 5) if self.robot_mode == 4 else None
        if (
            self._watchdog_s is not None
            and self.runtime_state == 2
            and self._watch_silence > self._watchdog_s
        ):
            if self._move is not None:
                self._move.begin_stop(now - self._move.t0, self.program_stop_decel)
            self._end_program(
                f"watchdog: no input_int_register_0 for {self._watchdog_s:.3f} s; program stopped"
            )
        m = self._move
        if m is None:
            return
        t = now - m.t0
        if self._protective_at is not None and now >= self._protective_at:
            self._protective_at = None
            m.stop = (t, m.s_at(t), 0.0, 1.0)  # halts at once
            self.safety_bits = 4
            self._protective_times.append(now)
            self._end_program("protective stop")
        s = m.s_at(t)
        if m.kind == 1:
            self.q = m.q0 + (m.qt - m.q0) * (s / m.d if m.d > 0 else 1.0)
        else:
            self.q, _ = ur5e_inverse(m.pose_at(s), self.q, iterations=2)
        self.tcp = ur5e_forward(self.q)
        if t >= m.end_t():
            self._move = None
            if not self._move_sync:
                self._async_progress(running=False)
            if self.runtime_state == 2 and (self._move_sync or self._stop_sync):
                self.out_int[0] = 2
            self._stop_sync = False

    def _script_received(self) -> None:
        self.scripts_received += 1
        if self.script_starts and self.remote_control and self.robot_mode == 7 and self.safety_bits == 1:
            self.runtime_state, self.out_int[0] = 2, 1
            self._async_progress(running=False)
            self._watch_silence = 0.0

    # --------------------------------------------------------------------------------------- RTDE
    def _rtde(self, conn: socket.socket) -> None:
        outputs: list[str] = []
        out_fmt = ">"
        inputs: dict[int, tuple[list[str], str]] = {}
        started = False
        next_send = 0.0
        period = self.period_s

        def send(kind: str, payload: bytes) -> None:
            conn.sendall(struct.pack(">HB", len(payload) + 3, ord(kind)) + payload)

        buf = b""
        while not self._stop.is_set():
            timeout = max(0.0, next_send - time.monotonic()) if started else 0.05
            readable, _, _ = select.select([conn], [], [], timeout)
            if readable:
                chunk = conn.recv(65536)
                if not chunk:
                    return
                buf += chunk
            while len(buf) >= 3:
                size, kind = struct.unpack(">HB", buf[:3])
                if len(buf) < size:
                    break
                payload, buf = buf[3:size], buf[size:]
                k = chr(kind)
                if k == "V":
                    send("V", b"\x01")
                elif k == "v":
                    send("v", struct.pack(">IIII", *CONTROLLER_VERSION))
                elif k == "O":
                    (frequency,) = struct.unpack(">d", payload[:8])
                    if frequency > 0:
                        period = 1.0 / min(frequency, 500.0)  # an e-Series controller streams up to 500 Hz
                        self.frequencies.append(frequency)
                    names = [n for n in payload[8:].decode().split(",") if n]
                    types = [rtde_type(n) or "NOT_FOUND" for n in names]
                    self.unknown_variables.update(n for n, t in zip(names, types) if t == "NOT_FOUND")
                    outputs = names
                    out_fmt = ">B" + "".join(TYPE_FORMATS.get(t, "") for t in types)
                    send("O", b"\x01" + ",".join(types).encode())
                elif k == "I":
                    names = [n for n in payload.decode().split(",") if n]
                    types = [rtde_type(n) or "NOT_FOUND" for n in names]
                    self.unknown_variables.update(n for n, t in zip(names, types) if t == "NOT_FOUND")
                    with self._lock:  # an input another connection writes is IN_USE (one writer each)
                        owners = [self._input_owner.get(n, id(conn)) for n in names]
                        if all(o == id(conn) for o in owners):
                            self._input_owner.update((n, id(conn)) for n in names)
                        else:
                            types = ["IN_USE" if o != id(conn) else t for o, t in zip(owners, types)]
                    rid = len(inputs) + 1
                    inputs[rid] = (names, ">" + "".join(TYPE_FORMATS.get(t, "") for t in types))
                    send("I", bytes([rid]) + ",".join(types).encode())
                elif k == "S":
                    started, next_send = True, time.monotonic()
                    send("S", b"\x01")
                elif k == "P":
                    started = False
                    send("P", b"\x01")
                elif k == "U" and payload[0] in inputs and "IN_USE" not in inputs[payload[0]][1]:
                    names, fmt = inputs[payload[0]]
                    with self._lock:
                        self._on_input(dict(zip(names, struct.unpack(fmt, payload[1:]))))
            if started and time.monotonic() >= next_send:
                next_send += period
                with self._lock:
                    if self._silent.is_set():
                        continue
                    flat: list[Any] = []
                    for n in outputs:
                        v = self._value(n)
                        if isinstance(v, np.ndarray | list | tuple):
                            flat.extend(v)
                        else:  # a scalar, or 0 for a variable the fake does not model: fill its shape
                            fmt = TYPE_FORMATS[rtde_type(n) or "DOUBLE"]
                            flat.extend([v] * (int(fmt[0]) if fmt[0].isdigit() else 1))
                send("U", struct.pack(out_fmt, 1, *flat))

    # --------------------------------------------------------------------------------------- dashboard
    def _dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        f = conn.makefile("rb")
        while not self._stop.is_set():
            readable, _, _ = select.select([conn], [], [], 0.05)
            if not readable:
                continue
            line = f.readline()
            if not line:
                return
            cmd = line.decode().strip()
            with self._lock:
                self.dashboard_log.append(cmd)
                reply = self._dashboard_reply(cmd)
            conn.sendall(reply.encode() + b"\n")
            if cmd == "quit":
                return

    def _dashboard_reply(self, cmd: str) -> str:
        modes = {3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 7: "RUNNING"}
        if cmd == "PolyscopeVersion":
            return POLYSCOPE
        if cmd == "get serial number":
            return "20235500001"
        if cmd == "is in remote control":
            return "true" if self.remote_control else "false"
        control = ("power on", "power off", "brake release", "unlock protective stop", "play", "stop")
        if cmd in control and not self.remote_control:
            return "Command is not allowed due to the robot being in local control"
        if cmd == "power on":
            if self.robot_mode == 3:
                self.robot_mode, self._mode_pending = 4, (time.monotonic() + self.power_step_s, 5)
            return "Powering on"
        if cmd == "power off":
            self.robot_mode, self._mode_pending = 3, None
            if self.runtime_state == 2:
                self._end_program("powered off")
            return "Powering off"
        if cmd == "brake release":
            if self.robot_mode in (4, 5):
                self._mode_pending = (time.monotonic() + self.power_step_s, 7)
            return "Brake releasing"
        if cmd == "robotmode":
            return f"Robotmode: {modes.get(self.robot_mode, 'UNKNOWN')}"
        if cmd in ("safetymode", "safetystatus"):
            return f"{cmd.capitalize()}: {'PROTECTIVE_STOP' if self.safety_bits & 4 else 'NORMAL'}"
        if cmd == "unlock protective stop":
            stopped_at = next((e for e in reversed(self._protective_times)), None)
            if self.safety_bits & 4 and stopped_at and time.monotonic() - stopped_at < self.unlock_delay_s:
                return (
                    f"Cannot unlock protective stop until {self.unlock_delay_s:g}s after occurrence. "
                    "Always inspect cause of protective stop before unlocking"
                )
            self.safety_bits = 1
            return "Protective stop releasing"
        if cmd == "stop":
            self.runtime_state = 1
            return "Stopped"
        if cmd == "quit":
            return "Disconnected"
        return f"could not understand: '{cmd}'"

    # --------------------------------------------------------------------------------------- script
    def _script(self, conn: socket.socket) -> None:
        received = b""
        while not self._stop.is_set():
            readable, _, _ = select.select([conn], [], [], 0.05)
            if readable:
                chunk = conn.recv(65536)
                if not chunk:
                    return
                received += chunk
            elif received:  # the upload went quiet: the controller runs the script
                with self._lock:
                    self._script_received()
                received = b""


def _serve_process(host: str, kwargs: dict[str, Any], pipe: Any) -> None:
    try:
        server = ControllerServer(host, **kwargs).__enter__()
    except OSError as exc:
        pipe.send(("error", str(exc)))
        return
    pipe.send(("ready", None))
    while True:
        try:
            cmd = pipe.recv()
        except (EOFError, OSError):
            cmd = "stop"
        if cmd == "silence":
            server.silence()
            pipe.send(("ok", None))
        elif cmd == "snapshot":
            pipe.send(("ok", server.snapshot()))
        elif isinstance(cmd, tuple) and cmd[0] == "set":
            server.set(cmd[1], cmd[2])
            pipe.send(("ok", None))
        else:
            server.__exit__(None, None, None)
            pipe.send(("ok", None))
            return


class FakeURController:
    """Run a :class:`ControllerServer` in a child process; ``with FakeURController("127.0.0.5", ...)``.

    Keyword arguments are those of ControllerServer (script_starts, protective_stop_on_move, powered,
    remote_control, unlock_delay_s...).
    """

    def __init__(self, host: str, **kwargs: Any) -> None:
        self.host = host
        self._kwargs = kwargs
        # forked from a server process that has imported this module and nothing else: a fresh process with
        # no ur_rtde threads or locks to inherit (a fork of the caller could), without a spawned interpreter's
        # ~0.8 s of CPU for the imports each time
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload([__name__])
        self._pipe, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve_process, args=(host, kwargs, child), daemon=True)

    def _call(self, cmd: Any) -> Any:
        self._pipe.send(cmd)
        if not self._pipe.poll(5.0):
            raise TimeoutError(f"fake UR controller on {self.host} did not answer {cmd!r}")
        return self._pipe.recv()[1]

    def __enter__(self) -> FakeURController:
        self._process.start()
        if not self._pipe.poll(30.0):  # the first starts the server, which imports numpy: slow when busy
            raise TimeoutError(f"fake UR controller on {self.host} did not start")
        status, detail = self._pipe.recv()
        if status != "ready":
            self._process.join(1.0)
            raise OSError(f"fake UR controller on {self.host}: {detail}")
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._call("stop")
        finally:
            self._process.join(3.0)
            if self._process.is_alive():
                self._process.kill()

    def silence(self) -> None:
        """Stop the RTDE data stream mid-session (sockets stay open)."""
        self._call("silence")

    def snapshot(self) -> dict[str, Any]:
        return self._call("snapshot")

    def set(self, name: str, value: Any) -> None:
        """Set a controller state variable mid-session (safety_bits=17 opens a guard: safeguard stop)."""
        self._call(("set", name, value))

    @property
    def pid(self) -> int | None:
        return self._process.pid
