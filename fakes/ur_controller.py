"""A fake Universal Robots controller on 127.0.0.N that the real ur_rtde client talks to.

It serves the three ports ur_rtde uses, per the public RTDE guide and the dashboard server manual:

* RTDE (30004): uint16 size + uint8 type header, big-endian; V (protocol version), v (controller version),
  O (output recipe), I (input recipes, numbered 1, 2, 3... per connection in arrival order), S/P (start,
  pause), U (data packages, sent every ``period_s`` after S; the client gives up after ~2.5 s of silence).
* Dashboard (29999): a greeting line, then one reply line per command line.
* Script (30003): receives the control script; the "script" then runs when ``script_starts``: runtime_state
  becomes PLAYING and output_int_register_0 = 1 (ready).

Motion follows ur_rtde's register handshake: the client writes input_int_register_0 (1 = moveJ, 3 = moveL,
255 = stop script) with targets in input_double_register_0..5 and speed/acceleration in 6..7; the fake
answers output_int_register_0 = 2 after ``move_time_s`` and goes back to 1 when the client clears the
command (0). moveJ updates the flange pose by UR5e forward kinematics; moveL sets the flange pose and
leaves the joints (the fake has no inverse kinematics). Fault cases: ``protective_stop_on_move``,
``script_starts=False``, :meth:`silence`; a refused connection is simply no fake on that address.
"""

from __future__ import annotations

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


def ur5e_forward(q: np.ndarray) -> np.ndarray:
    """Flange pose [x, y, z (m), rx, ry, rz (rotvec)] of a UR5e at joints q (rad), standard DH."""
    T = np.eye(4)
    for qi, d, a, al in zip(q, UR5E_D, UR5E_A, UR5E_ALPHA):
        ct, st, ca, sa = np.cos(qi), np.sin(qi), np.cos(al), np.sin(al)
        T = T @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]]
        )
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


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
        move_time_s: float = 0.05,
        period_s: float = 0.008,
        joints: tuple[float, ...] = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0),
    ) -> None:
        self.host = host
        self.script_starts = script_starts
        self.protective_stop_on_move = protective_stop_on_move
        self.move_time_s = move_time_s
        self.period_s = period_s
        self.q = np.array(joints, dtype=np.float64)
        self.tcp = ur5e_forward(self.q)
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.inputs: dict[str, Any] = {}
        self.robot_mode = 7  # RUNNING: powered, brakes released
        self.safety_bits = 1  # bit 0: normal mode; bit 2: protective stop
        self.runtime_state = 1  # STOPPED; 2 = PLAYING
        self.moves: list[tuple[int, list[float]]] = []  # (command, doubles 0..7) as received
        self.dashboard_log: list[str] = []
        self.unknown_variables: set[str] = set()
        self._pending: tuple[float, int, list[float]] | None = None
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
                "dashboard": list(self.dashboard_log),
                "q": self.q.copy(),
                "tcp": self.tcp.copy(),
                "unknown_variables": set(self.unknown_variables),
                "robot_mode": self.robot_mode,
                "safety_bits": self.safety_bits,
            }

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
        return self

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
            conn.close()

    def silence(self) -> None:
        """Stop sending RTDE data packages (sockets stay open), as a hung controller would."""
        self._silent.set()

    # --------------------------------------------------------------------------------------- state
    def _value(self, name: str) -> Any:
        m = _REGISTER.match(name)
        if m and m.group(1) == "output":
            idx = int(m.group(3))
            return {"int": self.out_int, "double": self.out_double}.get(m.group(2), [False] * 128)[idx]
        if name in ("actual_q", "target_q"):
            return self.q
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return self.tcp
        return {
            "timestamp": time.monotonic() - self._t0,
            "robot_mode": self.robot_mode,
            "safety_mode": 3 if self.safety_bits & 4 else 1,
            "safety_status": 3 if self.safety_bits & 4 else 1,
            "safety_status_bits": self.safety_bits,
            "runtime_state": self.runtime_state,
            "robot_status_bits": (1 if self.robot_mode >= 4 else 0) | (2 if self.runtime_state == 2 else 0),
            "speed_scaling": 1.0,
            "target_speed_fraction": 1.0,
        }.get(name, 0)

    def _on_input(self, values: dict[str, Any]) -> None:
        self.inputs.update(values)
        cmd = values.get("input_int_register_0")
        if cmd is None:
            return
        if cmd == 0 and self.out_int[0] == 2:
            self.out_int[0] = 1  # command cleared: ready for the next one
        elif cmd == 255:
            self.runtime_state, self.out_int[0] = 1, 0
        elif cmd and self.out_int[0] == 1 and self._pending is None:
            args = [float(self.inputs.get(f"input_double_register_{i}", 0.0)) for i in range(8)]
            self.moves.append((int(cmd), args))
            self.out_int[0] = 0  # busy
            if cmd in (1, 3) and self.protective_stop_on_move:
                self.safety_bits = 4  # protective stop: the motion never completes
                return
            self._pending = (time.monotonic() + (self.move_time_s if cmd in (1, 3) else 0.0), int(cmd), args)

    def _advance(self) -> None:
        if self._pending and time.monotonic() >= self._pending[0]:
            _, cmd, args = self._pending
            self._pending = None
            if cmd == 1:
                self.q = np.array(args[:6])
                self.tcp = ur5e_forward(self.q)
            elif cmd == 3:
                self.tcp = np.array(args[:6])
            self.out_int[0] = 2

    def _script_received(self) -> None:
        if self.script_starts:
            self.runtime_state, self.out_int[0] = 2, 1

    # --------------------------------------------------------------------------------------- RTDE
    def _rtde(self, conn: socket.socket) -> None:
        outputs: list[str] = []
        out_fmt = ">"
        inputs: dict[int, tuple[list[str], str]] = {}
        started = False
        next_send = 0.0

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
                    rid = len(inputs) + 1
                    inputs[rid] = (names, ">" + "".join(TYPE_FORMATS.get(t, "") for t in types))
                    send("I", bytes([rid]) + ",".join(types).encode())
                elif k == "S":
                    started, next_send = True, time.monotonic()
                    send("S", b"\x01")
                elif k == "P":
                    started = False
                    send("P", b"\x01")
                elif k == "U" and payload[0] in inputs:
                    names, fmt = inputs[payload[0]]
                    with self._lock:
                        self._on_input(dict(zip(names, struct.unpack(fmt, payload[1:]))))
            if started and time.monotonic() >= next_send:
                next_send += self.period_s
                with self._lock:
                    self._advance()
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
            return "true"
        if cmd == "power on":
            self.robot_mode = 5
            return "Powering on"
        if cmd == "power off":
            self.robot_mode = 3
            return "Powering off"
        if cmd == "brake release":
            self.robot_mode = 7
            return "Brake releasing"
        if cmd == "robotmode":
            return f"Robotmode: {modes.get(self.robot_mode, 'UNKNOWN')}"
        if cmd in ("safetymode", "safetystatus"):
            return f"{cmd.capitalize()}: {'PROTECTIVE_STOP' if self.safety_bits & 4 else 'NORMAL'}"
        if cmd == "unlock protective stop":
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
        except EOFError:
            cmd = "stop"
        if cmd == "silence":
            server.silence()
            pipe.send(("ok", None))
        elif cmd == "snapshot":
            pipe.send(("ok", server.snapshot()))
        else:
            server.__exit__(None, None, None)
            pipe.send(("ok", None))
            return


class FakeURController:
    """Run a :class:`ControllerServer` in a child process; ``with FakeURController("127.0.0.5", ...)``.

    Keyword arguments are those of ControllerServer (script_starts, protective_stop_on_move, move_time_s...).
    """

    def __init__(self, host: str, **kwargs: Any) -> None:
        self.host = host
        self._kwargs = kwargs
        ctx = multiprocessing.get_context("spawn")  # fork could inherit locks held by ur_rtde threads
        self._pipe, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve_process, args=(host, kwargs, child), daemon=True)

    def _call(self, cmd: str) -> Any:
        self._pipe.send(cmd)
        if not self._pipe.poll(5.0):
            raise TimeoutError(f"fake UR controller on {self.host} did not answer {cmd!r}")
        return self._pipe.recv()[1]

    def __enter__(self) -> FakeURController:
        self._process.start()
        if not self._pipe.poll(5.0):
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
