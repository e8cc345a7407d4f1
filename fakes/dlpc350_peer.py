"""A DLPC350 at the USB HID transport level, for tests: parses TI's packets strictly and answers as the
controller does (programmer's guide DLPU010, USB command table; reference API dlpc350_api.cpp).

It is written apart from the driver (offsets spelled out here, not imported), so a packing mistake in one does
not hide in the other. Every report written must be 65 bytes with report id 0; a header must have
destination 0, the reserved and NACK bits clear and the reply bit set; a command's data length must be what
the command table says; a read carries no data. Anything else fails the test at once (``ProtocolViolation``).
Commands the controller would refuse in its current state get a NACK reply: configuring while the sequence
runs, starting an unvalidated or invalid LUT, mailbox data with the mailbox closed.

``trigger_out`` is called once per pattern exposure while the sequence runs (VSYNC mode: on every
:meth:`vsync`; internal trigger: :meth:`run_internal` for a number of patterns), like TRIG_OUT_1. With
``autoplay`` a sequence started in internal-trigger mode (patterns from flash) plays its whole LUT at once,
as the controller does by itself once started.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

# command -> data bytes of a write (None: variable, the mailbox data); reads carry no data
WRITE_LENGTH: dict[int, int | None] = {
    0x0200: 1,  # POWER_CONTROL
    0x1A07: 1,  # LED_ENABLE
    0x1A1A: 1,  # LUT_VALID (start validation)
    0x1A1B: 1,  # DISP_MODE
    0x1A1D: 3,  # TRIG_OUT1_CTL
    0x1A22: 1,  # PAT_DISP_MODE
    0x1A23: 1,  # PAT_TRIG_MODE
    0x1A24: 1,  # PAT_START_STOP
    0x1A29: 8,  # PAT_EXPO_PRD
    0x1A31: 4,  # PAT_CONFIG
    0x1A32: 1,  # MBOX_ADDRESS
    0x1A33: 1,  # MBOX_CONTROL
    0x1A34: None,  # MBOX_DATA
}
READABLE = {
    0x0205,
    0x0200,
    0x1A07,
    0x1A0A,
    0x1A0B,
    0x1A0C,
    0x1A1A,
    0x1A1B,
    0x1A22,
    0x1A23,
    0x1A24,
    0x1A29,
    0x1A31,
}
CONFIG_COMMANDS = {0x1A1B, 0x1A22, 0x1A23, 0x1A29, 0x1A31, 0x1A32, 0x1A33, 0x1A34, 0x1A1D}
MIN_EXPOSURE_US = (0, 235, 700, 1570, 1700, 2000, 2500, 4500, 8333)  # by bit depth 1..8


class ProtocolViolation(AssertionError):
    """The host sent something the DLPC350 cannot parse."""


@dataclass
class Dlpc350State:
    standby: bool = True
    leds: int = 0x08  # LED_ENABLE: bit 3 sequencer control, bits 2:0 blue, green, red
    pattern_mode: bool = False
    source: int = 0  # PAT_DISP_MODE: 0 video port, 3 flash
    trigger_mode: int = 0  # 0 VSYNC, 1 internal/external
    exposure_us: int = 0
    period_us: int = 0
    config: tuple[int, int, int, int] = (0, 0, 0, 0)  # LUT entries - 1, repeat, trig out 2 - 1, images - 1
    trig_out1: tuple[int, int, int] = (0, 187, 187)
    mailbox: int = 0  # 0 closed, 1 image LUT, 2 pattern LUT
    address: int = 0
    pattern_lut: list[int] = field(default_factory=list)
    image_lut: list[int] = field(default_factory=list)
    validation: int | None = None  # LUT_VALID result once validated
    running: int = 0  # PAT_START_STOP: 0 stop, 1 pause, 2 start
    lut_position: int = 0


class Dlpc350Peer:
    """The controller behind :class:`drivers.dlpc350.HidTransport`: ``write(report)``, ``read(64, ms)``."""

    def __init__(
        self,
        *,
        trigger_out: Callable[[int], None] | None = None,
        hw_status: int = 0x01,
        autoplay: bool = False,
    ) -> None:
        self.state = Dlpc350State()
        self.trigger_out = trigger_out
        self.autoplay = autoplay
        self.hw_status = hw_status  # bit 0 init done; bits 6, 7 sequencer abort / error
        self.log: list[tuple[str, int, bytes]] = []  # (read|write, command, data)
        self.triggers = 0
        self._replies: list[bytes] = []
        self._partial: bytearray | None = None
        self._expect = 0

    # ----------------------------------------------------------------------------------------- transport
    def write(self, report: bytes) -> int:
        if len(report) != 65 or report[0] != 0:
            raise ProtocolViolation(
                f"a report is 65 bytes starting with report id 0, got {len(report)}: {report[:4]!r}"
            )
        body = report[1:]
        if self._partial is not None:  # a continuation report: 64 more message bytes
            self._partial += body
            if len(self._partial) >= self._expect:
                message, self._partial = bytes(self._partial[: self._expect]), None
                self._handle(message)
            return len(report)
        flags, seq, length = body[0], body[1], body[2] | body[3] << 8
        if flags & 0x07 or flags & 0x18 or flags & 0x20:
            raise ProtocolViolation(
                f"header flags {flags:#04x}: destination, reserved and NACK bits must be 0"
            )
        if not flags & 0x40:
            raise ProtocolViolation("the reply bit must be set (the driver waits for every answer)")
        if length < 2 or length > 512:
            raise ProtocolViolation(f"length {length} outside 2..512")
        message = body[:4] + body[4 : 4 + length]
        if 4 + length > 64:
            self._partial, self._expect = bytearray(body), 4 + length
            return len(report)
        if any(body[4 + length :]):
            raise ProtocolViolation("bytes after the message must be zero")
        del seq
        self._handle(bytes(message))
        return len(report)

    def read(self, size: int, timeout_ms: int) -> bytes:
        if size != 64:
            raise ProtocolViolation(f"reads are of one 64-byte report, asked {size}")
        return self._replies.pop(0) if self._replies else b""

    def close(self) -> None:
        pass

    # ----------------------------------------------------------------------------------------- messages
    def _reply(self, flags: int, seq: int, data: bytes = b"", nack: bool = False) -> None:
        out = bytes([flags | (0x20 if nack else 0), seq, len(data) & 0xFF, len(data) >> 8]) + data
        self._replies.append(out.ljust(64, b"\x00"))

    def _handle(self, message: bytes) -> None:
        flags, seq, length = message[0], message[1], message[2] | message[3] << 8
        command = message[4] | message[5] << 8  # little-endian: CMD3 first, then CMD2
        data = message[6 : 4 + length]
        if flags & 0x80:
            if data or command not in READABLE:
                raise ProtocolViolation(f"read of {command:04X} with {len(data)} data bytes")
            self.log.append(("read", command, b""))
            self._reply(flags, seq, self._read(command))
            return
        if command not in WRITE_LENGTH:
            raise ProtocolViolation(f"unknown or unwritable command {command:04X}")
        want = WRITE_LENGTH[command]
        if want is not None and len(data) != want:
            raise ProtocolViolation(f"command {command:04X} takes {want} data bytes, got {len(data)}")
        self.log.append(("write", command, bytes(data)))
        self._reply(flags, seq, nack=not self._write(command, bytes(data)))

    def _read(self, command: int) -> bytes:
        s = self.state
        le32 = int.to_bytes
        return {
            0x0205: le32(0x04000000, 4, "little") * 4,  # application, API, software config, sequence config
            0x0200: bytes([1 if s.standby else 0]),
            0x1A07: bytes([s.leds]),
            0x1A0A: bytes([self.hw_status]),
            0x1A0B: b"\x01",  # internal memory test passed
            0x1A0C: bytes([0x02 if s.running == 2 else 0x00]),
            0x1A1A: bytes([s.validation if s.validation is not None else 0x00]),
            0x1A1B: bytes([1 if s.pattern_mode else 0]),
            0x1A22: bytes([s.source]),
            0x1A23: bytes([s.trigger_mode]),
            0x1A24: bytes([s.running]),
            0x1A29: le32(s.exposure_us, 4, "little") + le32(s.period_us, 4, "little"),
            0x1A31: bytes(s.config),
        }[command]

    def _write(self, command: int, data: bytes) -> bool:
        """Apply a write; False means NACK."""
        s = self.state
        if command in CONFIG_COMMANDS and s.running:
            return False  # the sequence must be stopped before it is changed
        if command in CONFIG_COMMANDS:
            s.validation = None
        if command == 0x0200:
            s.standby = bool(data[0])
            return data[0] in (0, 1)
        if command == 0x1A07:
            s.leds = data[0]
            return data[0] < 0x10
        if command == 0x1A1B:
            s.pattern_mode = data[0] == 1
            return data[0] in (0, 1)
        if command == 0x1A22:
            s.source = data[0]
            return data[0] in (0, 3)
        if command == 0x1A23:
            s.trigger_mode = data[0]
            return data[0] in (0, 1, 2)
        if command == 0x1A29:
            s.exposure_us = int.from_bytes(data[:4], "little")
            s.period_us = int.from_bytes(data[4:], "little")
            return True
        if command == 0x1A31:
            s.config = (data[0], data[1], data[2], data[3])
            return data[1] in (0, 1)
        if command == 0x1A1D:
            s.trig_out1 = (data[0], data[1], data[2])
            return data[1] <= 213 and data[2] <= 213
        if command == 0x1A33:
            s.mailbox, s.address = data[0], 0
            if data[0] == 2:
                s.pattern_lut = []
            elif data[0] == 1:
                s.image_lut = []
            return data[0] in (0, 1, 2)
        if command == 0x1A32:
            s.address = data[0]
            return s.mailbox != 0
        if command == 0x1A34:
            if s.mailbox == 2:
                if len(data) % 3:
                    raise ProtocolViolation(f"pattern LUT data of {len(data)} bytes is not 3 per entry")
                s.pattern_lut = [int.from_bytes(data[i : i + 3], "little") for i in range(0, len(data), 3)]
                return True
            if s.mailbox == 1:
                s.image_lut = list(data)
                return True
            return False
        if command == 0x1A1A:
            if s.mailbox != 0:
                return False
            s.validation = self._validate()
            return True
        if command == 0x1A24:
            if data[0] == 2 and (
                s.validation is None or s.validation & 0x1F or not s.pattern_mode or s.standby
            ):
                return False  # not validated, invalid, or not in pattern mode
            s.running = data[0]
            s.lut_position = 0
            if self.autoplay and s.running == 2 and s.trigger_mode == 1:
                self.run_internal(len(s.pattern_lut))
            return data[0] in (0, 1, 2)
        return False

    def _validate(self) -> int:
        """LUT_VALID result: bit 0 exposure/period invalid, bit 1 pattern numbers invalid, bit 4 exposure and
        period closer than 230 us without being equal."""
        s, result = self.state, 0
        entries = s.config[0] + 1
        if len(s.pattern_lut) != entries:
            result |= 0x02
        depths = [(e >> 8) & 0xF for e in s.pattern_lut] or [1]
        if not all(1 <= d <= 8 for d in depths):
            result |= 0x02
        for e in s.pattern_lut:
            number, depth = (e >> 2) & 0x3F, (e >> 8) & 0xF
            if depth and number >= 24 // depth:
                result |= 0x02  # a 24-bit image holds 24 / depth patterns of that depth
        if s.source == 3 and len(s.image_lut) != s.config[3] + 1:
            result |= 0x02
        minimum = max(MIN_EXPOSURE_US[min(max(d, 1), 8)] for d in depths)
        if not minimum <= s.exposure_us <= s.period_us:
            result |= 0x01
        elif s.exposure_us != s.period_us and s.period_us - s.exposure_us < 230:
            result |= 0x10
        return result

    # ----------------------------------------------------------------------------------------- the light
    def vsync(self) -> bool:
        """A video frame arrives (VSYNC mode): with the sequence running, one pattern exposure and one
        TRIG_OUT_1 pulse per LUT entry. Returns whether the trigger fired."""
        s = self.state
        if s.running != 2 or s.trigger_mode != 0 or s.source != 0:
            return False
        self._fire()
        return True

    def run_internal(self, patterns: int) -> int:
        """Internal trigger: the sequencer exposes ``patterns`` LUT entries in a row; returns the pulses."""
        s = self.state
        if s.running != 2 or s.trigger_mode != 1:
            return 0
        fired = 0
        for _ in range(patterns):
            if s.lut_position >= len(s.pattern_lut):
                if not s.config[1]:
                    s.running = 0
                    break
                s.lut_position = 0
            self._fire()
            fired += 1
        return fired

    def _fire(self) -> None:
        s = self.state
        self.triggers += 1
        s.lut_position += 1
        if self.trigger_out is not None:
            self.trigger_out(s.lut_position - 1)


class SimPatternDisplay:
    """The DLPC350's video input in the simulated world: a streamed frame reaches the simulated projector
    (whose frame sync exposes a hardware-triggered simulated camera, as TRIG_OUT_1 would) only while
    the peer's sequencer runs; a frame streamed to a stopped sequencer fails the test."""

    def __init__(self, projector: Any, peer: Dlpc350Peer) -> None:
        self.projector, self.peer = projector, peer

    @property
    def size(self) -> tuple[int, int]:
        return self.projector.resolution

    @property
    def last_present_s(self) -> float:
        return self.projector.last_present_s

    def open(self) -> None:
        self.projector.connect()
        self.projector.set_power(True)

    def show(self, image: Any) -> None:
        if not self.peer.vsync():
            raise ProtocolViolation("a video frame was streamed while the pattern sequence was stopped")
        self.projector.show(image)

    def close(self) -> None:
        self.projector.close()
