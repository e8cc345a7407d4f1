"""A projector controlled over RS-232 by a command set from a YAML profile (e.g. Epson ESC/VP21).

Control (power, input, status) goes over the serial line; the pixels go over HDMI through a separate
:class:`PatternDisplay`, because the two are different links on the real device. The display is injected
(``display=``) or built from ``options.display`` (a :class:`drivers.hdmi_display.HdmiDisplay` full-screen
window); it opens with :meth:`SerialProjector.connect` and must have the projector's resolution.
Every exchange is framed by the profile's prompt, bounded by its timeout and retried a bounded number of
times after a timeout or a garbled reply; a refusal (``ERR``) is a DeviceFault and is not retried, except for
commands whose profile entry has ``retry_refused_s`` (``SOURCE``: the projector refuses it while the HDMI
signal settles, right after the display opened). Power-on returns once ``PWR?`` reads a powered state and
reports a lamp or other failure as soon as the projector shows it (polled every ``timing.power_poll_s``).
Waits run on ``clock`` (the host's monotonic clock; tests pass a simulated one).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Annotated, Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cell.config import ProjectorConfig, Strict, validate
from cell.contracts import Clock, ProjectorHooks, ProjectorSource, ProjectorStatus, SystemClock
from cell.errors import DeviceError, DeviceFault, DeviceProtocolError, DeviceTimeout
from drivers.hdmi_display import HdmiDisplay, HdmiDisplayOptions, open_at_projector_resolution
from drivers.projector_profile import ProjectorProfile, load_profile
from drivers.serial_transport import PySerialTransport, Transport, read_frame


class PatternDisplay(Protocol):
    """Where the pixels go: a full-screen output on the projector's HDMI input."""

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the output, px; valid once open."""
        ...

    def open(self) -> None: ...

    def show(self, image: NDArray[np.uint8]) -> object: ...

    def close(self) -> None: ...


class _Refused(DeviceFault):
    """The projector answered its error reply: it understood the command and will not do it now."""

    def __init__(self, device: str, reason: str) -> None:
        super().__init__(device, reason)
        self.reason = reason


class SerialProjectorOptions(Strict):
    """``sensor.projector.options`` for ``driver: serial``."""

    port: str = Field(description="serial device (/dev/ttyUSB0) or pyserial URL (spy://..., rfc2217://...)")
    profile: str = Field("epson_escvp21", description="profile name in drivers/profiles/ or a YAML path")
    reply_timeout_s: Annotated[float, Field(gt=0, le=600)] | None = None
    retries: Annotated[int, Field(ge=0, le=10)] | None = None
    display: HdmiDisplayOptions | None = Field(
        None, description="the HDMI pattern window (monitor index, mode, ...); None: pass display= instead"
    )


class SerialProjector(ProjectorHooks):
    """Projector over a serial control line plus an optional HDMI pattern display (Projector contract)."""

    def __init__(
        self,
        config: ProjectorConfig,
        *,
        transport: Transport | None = None,
        display: PatternDisplay | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.name = config.name
        self._config = config
        self.timing = config.timing
        self.clock: Clock = clock or SystemClock()
        self.options = validate(
            SerialProjectorOptions, dict(config.options), f"projector '{config.name}' options"
        )
        self.profile: ProjectorProfile = load_profile(self.options.profile)
        timing = self.profile.timing
        self._timeout_s = self.options.reply_timeout_s or timing.reply_timeout_s
        self._retries = timing.retries if self.options.retries is None else self.options.retries
        self._transport = transport
        self._owns_transport = transport is None
        if display is None and self.options.display is not None:
            display = HdmiDisplay(self.options.display, name=f"{config.name} HDMI")
        self._display = display
        self._sequence: list[NDArray[np.uint8]] = []
        self._next = 0

    # ----------------------------------------------------------------------------------------- link
    @property
    def resolution(self) -> tuple[int, int]:
        return (self._config.width_px, self._config.height_px)

    @property
    def last_present_s(self) -> float:
        """The display's last present stamp (its clock: time.monotonic), NaN if it does not stamp."""
        return float(getattr(self._display, "last_present_s", math.nan))

    def connect(self) -> None:
        """Open the port, check that the projector answers the null command, open the pattern display."""
        if self._transport is None:
            s = self.profile.serial
            try:
                self._transport = PySerialTransport(
                    self.options.port,
                    baudrate=s.baudrate,
                    bytesize=s.bytesize,
                    parity=s.parity,
                    stopbits=s.stopbits,
                )
            except Exception as exc:  # pyserial raises SerialException/OSError/ValueError for a bad port
                raise DeviceFault(self.name, f"cannot open serial port {self.options.port!r}: {exc}") from exc
        self._exchange("ping")
        if self._display is not None:
            open_at_projector_resolution(self._display, self.resolution, self.name)

    def close(self) -> None:
        if self._transport is not None and self._owns_transport:
            self._transport.close()
            self._transport = None
        if self._display is not None:
            self._display.close()

    def _exchange(self, command: str, **fields: str) -> str | None:
        """Send one profile command; return the reply's ``value`` for queries, None for set commands."""
        cmd = self.profile.command(command)
        if cmd is None:
            raise DeviceFault(self.name, f"profile '{self.profile.name}' has no '{command}' command")
        if self._transport is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        p = self.profile
        text = cmd.send.format(**fields)
        data = (text + p.terminator).encode(p.encoding)
        prompt = p.prompt.encode(p.encoding)
        timeout_s = (
            cmd.timeout_s
            if cmd.timeout_s is not None and self.options.reply_timeout_s is None
            else self._timeout_s
        )
        last: DeviceError | None = None
        attempts = self._retries + 1
        for attempt in range(1, attempts + 1):
            what = f"{text!r} (attempt {attempt}/{attempts})"
            if p.timing.settle_s > 0:
                self.clock.sleep(p.timing.settle_s)
            self._transport.discard_input()
            self._transport.write(data)
            try:
                frame = read_frame(self._transport, prompt, timeout_s, self.name, what)
            except (DeviceTimeout, DeviceProtocolError) as exc:
                last = exc
                continue
            lines = [ln.strip() for ln in frame.decode(p.encoding, errors="replace").split(p.terminator)]
            lines = [ln for ln in lines if ln]
            if lines == [p.error_reply]:
                raise _Refused(
                    self.name,
                    f"projector refused {text!r} ({p.error_reply}); check its state "
                    "(warming up, no signal on the input, lamp fault) and its error status",
                )
            if cmd.reply is None:
                if not lines:
                    return None
                last = DeviceProtocolError(self.name, f"{what}: expected only {p.prompt!r}, got {frame!r}")
                continue
            match = re.fullmatch(cmd.reply, lines[0]) if len(lines) == 1 else None
            if match:
                return match["value"]
            last = DeviceProtocolError(self.name, f"{what}: reply {frame!r} does not match {cmd.reply!r}")
        assert last is not None
        raise last

    def _exchange_until_accepted(self, command: str, **fields: str) -> str | None:
        """:meth:`_exchange`, retrying a refusal for the command's ``retry_refused_s`` (on ``clock``)."""
        cmd = self.profile.command(command)
        patience = cmd.retry_refused_s if cmd is not None else 0.0
        deadline = self.clock.now() + patience
        while True:
            try:
                return self._exchange(command, **fields)
            except _Refused as exc:
                if self.clock.now() >= deadline:
                    if patience > 0:
                        raise DeviceFault(
                            self.name, f"{exc.reason} (still after {patience:g} s of retries)"
                        ) from None
                    raise
            self.clock.sleep(self.profile.timing.refused_retry_interval_s)

    # ----------------------------------------------------------------------------------------- control
    def set_power(self, on: bool) -> None:
        """Power off, or power on and wait until the projector projects: a lamp or other failure is a
        DeviceFault as soon as the projector reports it (not after the warm-up timeout)."""
        if not on:
            self._exchange("power_off")
            return
        self._exchange("power_on")
        t = self.profile.timing
        deadline = self.clock.now() + t.power_on_s
        while True:
            pwr = self._exchange("power_query")
            assert pwr is not None
            if pwr in self.profile.powered_states:
                return
            code = self._query_optional("error_query")
            state = self.profile.power_states.get(pwr, f"unknown power state {pwr}")
            if code is not None and int(code, 16) != 0:
                why = self.profile.error_codes.get(code, f"error code {code}")
                raise DeviceFault(self.name, f"power-on failed: {why} (power state: {state})")
            if pwr not in self.profile.warming_states:
                raise DeviceFault(self.name, f"power-on failed: the projector went to '{state}'")
            if self.clock.now() >= deadline:
                raise DeviceTimeout(self.name, f"still '{state}' {t.power_on_s:g} s after power-on")
            self.clock.sleep(t.power_poll_s)

    def set_source(self, source: ProjectorSource) -> None:
        """HDMI: select the HDMI input and unmute; INTERNAL: mute to the projector's own black screen."""
        has_mute = self.profile.command("mute_set") is not None
        if source is ProjectorSource.HDMI:
            self._exchange_until_accepted("source_set", code=self.profile.sources["hdmi"])
            if has_mute:
                self._exchange("mute_set", state="OFF")
        elif has_mute:
            self._exchange("mute_set", state="ON")
        else:
            raise DeviceFault(
                self.name, f"profile '{self.profile.name}' has no command for the internal screen"
            )

    def _query_optional(self, command: str) -> str | None:
        return self._exchange(command) if self.profile.command(command) is not None else None

    def status(self) -> ProjectorStatus:
        """Power, input, lamp hours and errors; temperature is NaN if the command set cannot query it."""
        pwr = self._exchange("power_query")
        assert pwr is not None
        powered = pwr in self.profile.powered_states
        errors: list[str] = []
        state = self.profile.power_states.get(pwr, f"unknown power state {pwr}")
        if "abnormal" in state:
            errors.append(state)
        code = self._query_optional("error_query")
        if code is not None and int(code, 16) != 0:
            errors.append(self.profile.error_codes.get(code, f"error code {code}"))
        lamp = self._query_optional("lamp_query")
        temperature = self._query_optional("temperature_query")
        source = ProjectorSource.INTERNAL
        if powered:  # input queries are refused in standby
            muted = self._query_optional("mute_query") == "ON"
            if self._query_optional("source_query") == self.profile.sources["hdmi"] and not muted:
                source = ProjectorSource.HDMI
        return ProjectorStatus(
            powered=powered,
            source=source,
            lamp_hours=float(lamp) if lamp is not None else math.nan,
            temperature_c=float(temperature) if temperature is not None else math.nan,
            errors=tuple(errors),
        )

    # ----------------------------------------------------------------------------------------- pixels
    def _check(self, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
        w, h = self.resolution
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.shape != (h, w):
            raise DeviceProtocolError(
                self.name,
                f"image must be uint8 of shape ({h}, {w}) to show pixel-exact, got {img.dtype} {img.shape}",
            )
        return img

    def show(self, image: NDArray[np.uint8]) -> None:
        img = self._check(image)
        if self._display is None:
            raise DeviceFault(self.name, "no HDMI pattern display attached; pass display= to SerialProjector")
        self._display.show(img)

    @property
    def current_image(self) -> NDArray[np.uint8]:
        """The frame last presented on HDMI, read back from the display (AttributeError if it cannot)."""
        if self._display is None or not hasattr(self._display, "current_image"):
            raise AttributeError(f"{self.name}: the pattern display cannot read back what it shows")
        return self._display.current_image

    def load_sequence(self, images: Sequence[NDArray[np.uint8]]) -> None:
        self._sequence = [self._check(im).copy() for im in images]
        self._next = 0

    def step(self) -> int:
        """Show the next loaded image and return its index; the sequence repeats after its last image."""
        if not self._sequence:
            raise DeviceProtocolError(self.name, "step() without a loaded sequence; call load_sequence first")
        index = self._next
        self.show(self._sequence[index])
        self._next = (index + 1) % len(self._sequence)
        return index
