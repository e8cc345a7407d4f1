"""TI DLPC350 (DLP LightCrafter 4500 class) projector over USB HID, in pattern-sequence mode.

Packets follow TI's *DLPC350 Programmer's Guide* (DLPU010) and its reference API: a 64-byte HID report (plus
report id 0 on write) holding flags (bit 7 read, bit 6 reply wanted, bit 5 NACK in replies, bits 2:0
destination 0), a sequence byte, a little-endian length, then the 16-bit command (CMD2 << 8 | CMD3, stored
little-endian) and its data. A message longer than one report continues in plain 64-byte reports. Replies
carry the same header and the data at byte 4.

Pattern sequence, two sources (``options.source``):

* ``video``: patterns are streamed over HDMI as 8-bit grey frames (R=G=B) through a pattern display (the
  same :class:`drivers.hdmi_display.HdmiDisplay` as the serial projector), the controller runs a one-entry
  LUT (G7:G0, 8 bits, a new buffer every frame) on each VSYNC, with exposure and period of one frame.
* ``flash``: patterns stored in the controller's flash images by TI's GUI (24 one-bit planes per image); the
  LUT walks ``options.flash_images`` bit plane by bit plane on the internal trigger at ``exposure_us`` /
  ``period_us``. The driver cannot check the stored content, only the count.

Either way TRIG_OUT_1 fires once per pattern exposure, into the camera's trigger line: :meth:`run_sequence`
flushes the camera, starts the sequencer, grabs one frame per pattern and places them by frame id.
Commands are validated by the controller (LUT_VALID) before a start; a NACK is a DeviceFault naming the
command. ``hidapi`` (PyPI) is imported only when a real device is opened.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated, Literal, Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cell.config import ProjectorConfig, Strict, validate
from cell.contracts import (
    Camera,
    Clock,
    Frame,
    ProjectorHooks,
    ProjectorSource,
    ProjectorStatus,
    SystemClock,
    TriggerMode,
    expected_frame_id,
    frames_by_id,
    grab_ready,
)
from cell.errors import ConfigError, DeviceFault, DeviceProtocolError, DeviceTimeout
from drivers.hdmi_display import HdmiDisplay, HdmiDisplayOptions, open_at_projector_resolution

if TYPE_CHECKING:
    from drivers.serial_projector import PatternDisplay

VID, PID = 0x0451, 0x6401  # Texas Instruments, DLPC350 (LightCrafter 4500)
REPORT = 64
FIRST_DATA = REPORT - 6  # data bytes after header and command in the first report

# (CMD2, CMD3) of the commands used, from the programmer's guide's USB command table
GET_VERSION = 0x0205
POWER_CONTROL = 0x0200
STATUS_HW, STATUS_SYS, STATUS_MAIN = 0x1A0A, 0x1A0B, 0x1A0C
LED_ENABLE = 0x1A07
LUT_VALID = 0x1A1A
DISP_MODE = 0x1A1B
TRIG_OUT1_CTL = 0x1A1D
PAT_DISP_MODE = 0x1A22
PAT_TRIG_MODE = 0x1A23
PAT_START_STOP = 0x1A24
PAT_EXPO_PRD = 0x1A29
PAT_CONFIG = 0x1A31
MBOX_ADDRESS = 0x1A32
MBOX_CONTROL = 0x1A33
MBOX_DATA = 0x1A34

HW_STATUS_ERRORS = {
    1: "incompatible controller or DMD",
    2: "DMD reset controller error",
    3: "forced swap error",
    6: "sequencer abort",
    7: "sequencer error",
}
LUT_ERRORS = {
    0: "exposure or frame period invalid",
    1: "pattern numbers in the LUT invalid",
    2: "trigger out 1 overlaps (continuous trigger or black sectors)",
    3: "post-sector vector missing before an externally triggered one",
    4: "frame period and exposure differ by less than 230 us",
}
LED_SEQUENCER = 0x08  # LED_ENABLE bit 3: the sequencer switches the LEDs (bits 2:0 manual blue/green/red)
TRIG_ZERO, TRIG_STEP_NS = 187, 107.136  # TRIG_OUT1 edge delay: 0xBB is no delay, steps of 107.136 ns
MIN_EXPOSURE_US = {1: 235, 2: 700, 3: 1570, 4: 1700, 5: 2000, 6: 2500, 7: 4500, 8: 8333}  # per bit depth


class HidTransport(Protocol):
    """What the driver needs of a HID device: report writes (with report id) and 64-byte reads."""

    def write(self, report: bytes) -> int: ...

    def read(self, size: int, timeout_ms: int) -> bytes: ...

    def close(self) -> None: ...


class HidapiTransport:
    """The real device through the ``hidapi`` package (cython-hidapi)."""

    def __init__(self, name: str, serial: str | None = None, path: str | None = None) -> None:
        try:
            import hid
        except ImportError as exc:
            raise ImportError(f"{exc}; pip install hidapi") from exc
        self._device = hid.device()
        try:
            if path:
                self._device.open_path(path.encode())
            else:
                self._device.open(VID, PID, serial or None)
        except OSError as exc:
            raise DeviceFault(
                name,
                f"cannot open the DLPC350 over USB HID ({VID:04x}:{PID:04x} {serial or ''}): {exc}; "
                "check the USB cable and the udev rule for hidraw access",
            ) from exc

    def write(self, report: bytes) -> int:
        return int(self._device.write(report))

    def read(self, size: int, timeout_ms: int) -> bytes:
        return bytes(self._device.read(size, timeout_ms))

    def close(self) -> None:
        self._device.close()


def encode(command: int, data: bytes, *, read: bool, seq: int) -> list[bytes]:
    """The HID reports (each with report id 0) of one message."""
    flags = (0x80 if read else 0x00) | 0x40  # reply wanted, destination 0 (projector control)
    body = struct.pack("<H", command) + data
    message = struct.pack("<BBH", flags, seq & 0xFF, len(body)) + body
    chunks = [message[: 4 + 2 + FIRST_DATA]] + [
        message[i : i + REPORT] for i in range(4 + 2 + FIRST_DATA, len(message), REPORT)
    ]
    return [b"\x00" + c.ljust(REPORT, b"\x00") for c in chunks]


class Dlpc350Options(Strict):
    """``sensor.projector.options`` for ``driver: dlpc350``."""

    serial: str | None = Field(None, description="USB serial number when several controllers are attached")
    hid_path: str | None = Field(None, description="hidraw path instead of VID/PID/serial")
    source: Literal["video", "flash"] = "video"
    flash_images: list[Annotated[int, Field(ge=0, le=255)]] = Field(
        default_factory=list, description="flash: image indices holding the patterns, 24 one-bit planes each"
    )
    exposure_us: Annotated[int, Field(ge=235, le=2_000_000)] | None = Field(
        None, description="flash: pattern exposure; video: one frame period"
    )
    period_us: Annotated[int, Field(ge=235, le=2_000_000)] | None = None
    trigger_out_delay_us: Annotated[float, Field(ge=-20.0, le=2.7)] = 0.0
    reply_timeout_ms: Annotated[int, Field(gt=0, le=60000)] = 2000
    display: HdmiDisplayOptions | None = Field(None, description="video: the HDMI pattern window")


class Dlpc350Projector(ProjectorHooks):
    """Projector contract plus :meth:`run_sequence` on a DLPC350 (pattern-sequence mode)."""

    def __init__(
        self,
        config: ProjectorConfig,
        *,
        transport: HidTransport | None = None,
        display: PatternDisplay | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.name = config.name
        self._config = config
        self.timing = config.timing
        self.clock: Clock = clock or SystemClock()
        self.options = validate(Dlpc350Options, dict(config.options), f"projector '{config.name}' options")
        o = self.options
        if o.source == "flash" and (not o.flash_images or o.exposure_us is None):
            raise ConfigError(
                "a flash pattern sequence needs options.flash_images and options.exposure_us",
                field="sensor.projector.options",
            )
        if display is None and o.display is not None:
            display = HdmiDisplay(o.display, name=f"{config.name} HDMI")
        self._display = display
        self._transport = transport
        self._owns_transport = transport is None
        self._seq = 0
        self._sequence: list[NDArray[np.uint8]] = []
        self._next = 0
        self._count = 0
        self._running = False
        self._programmed = False

    # ----------------------------------------------------------------------------------------- link
    @property
    def resolution(self) -> tuple[int, int]:
        return (self._config.width_px, self._config.height_px)

    @property
    def last_present_s(self) -> float:
        return float(getattr(self._display, "last_present_s", math.nan))

    def connect(self) -> None:
        """Open USB HID, read the firmware version (the controller answers), open the pattern display."""
        if self._transport is None:
            self._transport = HidapiTransport(self.name, self.options.serial, self.options.hid_path)
        self.version = self._read(GET_VERSION, 16)
        if self._display is not None and self.options.source == "video":
            open_at_projector_resolution(self._display, self.resolution, self.name)

    def close(self) -> None:
        if self._transport is not None and self._owns_transport:
            self._transport.close()
            self._transport = None
        if self._display is not None:
            self._display.close()

    # ----------------------------------------------------------------------------------------- messages
    def _send(self, command: int, data: bytes, *, read: bool) -> bytes:
        if self._transport is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        self._seq = (self._seq + 1) & 0xFF
        for report in encode(command, data, read=read, seq=self._seq):
            if self._transport.write(report) != len(report):
                raise DeviceProtocolError(self.name, f"short HID write of command {command:04X}")
        reply = self._transport.read(REPORT, self.options.reply_timeout_ms)
        if not reply:
            raise DeviceTimeout(
                self.name, f"no reply to command {command:04X} within {self.options.reply_timeout_ms} ms"
            )
        if len(reply) < 4:
            raise DeviceProtocolError(self.name, f"reply to {command:04X} is {len(reply)} bytes")
        flags, seq, length = struct.unpack("<BBH", reply[:4])
        if flags & 0x20:
            raise DeviceFault(self.name, f"controller refused command {command:04X} (NACK); check the mode")
        if seq != self._seq:
            raise DeviceProtocolError(self.name, f"reply sequence {seq} to message {self._seq}")
        return reply[4 : 4 + length]

    def _write(self, command: int, data: bytes) -> None:
        self._send(command, data, read=False)

    def _read(self, command: int, size: int, param: bytes = b"") -> bytes:
        data = self._send(command, param, read=True)
        if len(data) < size:
            raise DeviceProtocolError(
                self.name, f"reply to {command:04X} has {len(data)} bytes, expected {size}"
            )
        return data[:size]

    # ----------------------------------------------------------------------------------------- control
    def set_power(self, on: bool) -> None:
        self._write(POWER_CONTROL, bytes([0 if on else 1]))  # 0 normal, 1 standby

    def set_source(self, source: ProjectorSource) -> None:
        """HDMI: pattern mode from the video port (or flash), LEDs under sequencer control; INTERNAL:
        sequencer stopped and LEDs off (a dark projector)."""
        self._stop()
        if source is ProjectorSource.HDMI:
            self._write(DISP_MODE, b"\x01")
            self._write(PAT_DISP_MODE, b"\x00" if self.options.source == "video" else b"\x03")
            self._write(LED_ENABLE, bytes([LED_SEQUENCER]))
        else:
            self._write(LED_ENABLE, b"\x00")

    def status(self) -> ProjectorStatus:
        """Power, source (pattern mode and sequencer state) and the status registers' errors. LEDs have no
        lamp hours (reported 0) and the controller no temperature query (NaN)."""
        powered = self._read(POWER_CONTROL, 1)[0] == 0
        hw, sys_, _main = (self._read(c, 1)[0] for c in (STATUS_HW, STATUS_SYS, STATUS_MAIN))
        errors = [why for bit, why in HW_STATUS_ERRORS.items() if hw & (1 << bit)]
        if not hw & 1:
            errors.append("internal initialisation failed")
        if not sys_ & 1:
            errors.append("internal memory test failed")
        pattern = self._read(DISP_MODE, 1)[0] == 1
        lit = self._read(LED_ENABLE, 1)[0] & LED_SEQUENCER
        return ProjectorStatus(
            powered=powered,
            source=ProjectorSource.HDMI if powered and pattern and lit else ProjectorSource.INTERNAL,
            lamp_hours=0.0,
            temperature_c=math.nan,
            errors=tuple(errors),
        )

    # ----------------------------------------------------------------------------------------- sequence
    def _program(self, count: int) -> None:
        """Stop, load the LUT, exposure/period and trigger out for ``count`` patterns, validate."""
        o = self.options
        self._stop()
        self._write(DISP_MODE, b"\x01")
        if o.source == "video":
            period = round(1e6 / self.timing.refresh_hz)
            exposure = period
            entries = [_lut_word(trigger=0, pattern=0, bits=8, leds=7, swap=True)]  # G7:G0 of each new frame
            self._write(PAT_DISP_MODE, b"\x00")
            self._write(PAT_TRIG_MODE, b"\x00")  # VSYNC
            images = 1
        else:
            exposure = o.exposure_us or 0
            period = o.period_us or exposure
            if count > 24 * len(o.flash_images) or count > 128:
                raise ConfigError(
                    f"{count} patterns, options.flash_images hold {24 * len(o.flash_images)} (LUT max 128)",
                    field="sensor.projector.options.flash_images",
                )
            entries = [
                _lut_word(trigger=0 if k == 0 else 3, pattern=k % 24, bits=1, leds=7, swap=k % 24 == 0)
                for k in range(count)
            ]
            images = math.ceil(count / 24)
            self._write(PAT_DISP_MODE, b"\x03")
            self._write(PAT_TRIG_MODE, b"\x01")  # internal trigger
        bits = 8 if o.source == "video" else 1
        if exposure < MIN_EXPOSURE_US[bits] or exposure > period:
            raise ConfigError(
                f"DLPC350 exposure {exposure} us for {bits}-bit patterns must lie in "
                f"{MIN_EXPOSURE_US[bits]} us .. the period {period} us",
                field="sensor.projector.options.exposure_us",
            )
        self._write(PAT_EXPO_PRD, struct.pack("<II", exposure, period))
        rising = round(TRIG_ZERO + o.trigger_out_delay_us * 1000 / TRIG_STEP_NS)
        self._write(TRIG_OUT1_CTL, bytes([0, rising, TRIG_ZERO]))  # not inverted; falling edge undelayed
        self._write(
            PAT_CONFIG,
            bytes([len(entries) - 1, 1 if o.source == "video" else 0, len(entries) - 1, images - 1]),
        )
        if o.source == "flash":
            self._write(MBOX_CONTROL, b"\x01")
            self._write(MBOX_ADDRESS, b"\x00")
            self._write(MBOX_DATA, bytes(o.flash_images[:images]))
        self._write(MBOX_CONTROL, b"\x02")
        self._write(MBOX_ADDRESS, b"\x00")
        self._write(MBOX_DATA, b"".join(struct.pack("<I", e)[:3] for e in entries))
        self._write(MBOX_CONTROL, b"\x00")
        self._write(LUT_VALID, b"\x00")
        deadline = self.clock.now() + 5.0
        while (state := self._read(LUT_VALID, 1)[0]) & 0x80:
            if self.clock.now() > deadline:
                raise DeviceTimeout(self.name, "pattern LUT validation did not finish within 5 s")
            self.clock.sleep(0.01)
        problems = [why for bit, why in LUT_ERRORS.items() if state & (1 << bit)]
        if problems:
            raise DeviceFault(self.name, f"pattern sequence refused by the controller: {'; '.join(problems)}")
        self._programmed = True

    def load_sequence(self, images: Sequence[NDArray[np.uint8]]) -> None:
        """Video: keep the images (streamed frame by frame); flash: only their count (content is stored)."""
        w, h = self.resolution
        for k, im in enumerate(images):
            a = np.asarray(im)
            if a.dtype != np.uint8 or a.shape != (h, w):
                raise DeviceProtocolError(
                    self.name, f"image {k} must be uint8 ({h}, {w}), got {a.dtype} {a.shape}"
                )
        self._sequence = [np.asarray(im).copy() for im in images]
        self._count = len(self._sequence)
        self._next = 0
        self._program(self._count)

    def _start(self) -> None:
        if not self._running:
            self._write(PAT_START_STOP, b"\x02")
            self._running = True

    def _stop(self) -> None:
        self._write(PAT_START_STOP, b"\x00")
        self._running = False

    def show(self, image: NDArray[np.uint8]) -> None:
        """Stream one frame (video source); the sequencer is started first: it shows video frames only while
        it runs. Needs a loaded (validated) sequence."""
        w, h = self.resolution
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.shape != (h, w):
            raise DeviceProtocolError(
                self.name, f"image must be uint8 ({h}, {w}), got {img.dtype} {img.shape}"
            )
        if self._display is None or self.options.source != "video":
            raise DeviceFault(self.name, "show() needs source 'video' and an HDMI pattern display")
        if not self._programmed:
            self._program(1)
        self._start()
        self._display.show(np.asarray(image))

    def step(self) -> int:
        """Video: start the sequencer if needed and stream the next image; flash: not possible one by one."""
        if not self._sequence:
            raise DeviceProtocolError(self.name, "step() without a loaded sequence; call load_sequence first")
        if self.options.source != "video":
            raise DeviceFault(self.name, "a flash sequence runs by itself: use run_sequence()")
        index = self._next
        self.show(self._sequence[index])
        self._next = (index + 1) % len(self._sequence)
        return index

    def run_sequence(self, camera: Camera, count: int, timeout_ms: float) -> list[Frame | None]:
        """Flush the camera, start the sequence, grab ``count`` frames (one per trigger out), stop, and check
        the controller's status; frames are placed by id (None where one was lost)."""
        settings = getattr(camera, "settings", None)
        if settings is not None and TriggerMode(settings.trigger) is not TriggerMode.HARDWARE:
            raise DeviceFault(camera.name, "run_sequence needs hardware trigger on the line from TRIG_OUT_1")
        if count != self._count:
            raise DeviceProtocolError(self.name, f"{count} frames asked, {self._count} patterns loaded")
        flush = getattr(camera, "flush", None)
        if flush is not None:
            flush()
        first = expected_frame_id(camera)
        self._next = 0
        self._start()
        try:
            received: list[Frame] = []
            if self.options.source == "video":
                for image in self._sequence:
                    self.show(image)
                    received += grab_ready(camera)  # the camera holds only a few frames: fetch as they come
            frames = frames_by_id(camera, count, timeout_ms, first_id=first, received=received)
        finally:
            self._stop()
        hw = self._read(STATUS_HW, 1)[0]
        if hw & 0xC0:
            raise DeviceFault(
                self.name, "sequencer abort/error during the sequence; check exposure and trigger"
            )
        return frames


def _lut_word(*, trigger: int, pattern: int, bits: int, leds: int, swap: bool) -> int:
    """A pattern LUT entry: trigger type 1:0, pattern number 7:2, bit depth 11:8, LEDs 14:12, swap 18."""
    return (
        (trigger & 3)
        | (pattern & 0x3F) << 2
        | (bits & 0xF) << 8
        | (leds & 7) << 12
        | (1 << 18 if swap else 0)
    )
