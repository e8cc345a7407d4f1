"""Simulated projector: holds the image it shows, which the simulated camera renders onto the scene.

Timing is the real device's: :meth:`SimProjector.show` blocks until the next vertical blank of the input
(``timing.refresh_hz``) and stamps that present like :class:`drivers.hdmi_display.HdmiDisplay`; the frame
lights the scene ``latency_s`` later (the projector's input lag: ``options.latency_frames`` refresh periods,
default 2, a property of the simulated world the cell does not know). The frame sync output fires when the
light starts. :meth:`SimProjector.emission` tells the camera which images lit the scene during an exposure.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.config import ProjectorConfig
from cell.contracts import (
    Camera,
    Frame,
    ProjectorHooks,
    ProjectorSource,
    ProjectorStatus,
    TriggerMode,
    expected_frame_id,
    frames_by_id,
    grab_ready,
)
from cell.errors import ConfigError, DeviceFault, DeviceProtocolError, DeviceTimeout
from fakes.clock import SimClock

AMBIENT_TEMPERATURE_C = 25.0
RUNNING_TEMPERATURE_C = 42.0  # a DLP projector's reported temperature once warm
DEFAULT_LATENCY_FRAMES = 2.0  # input lag of a typical projector: scaler + DMD sequence
HISTORY_S = 2.0  # how far back the emission timeline is kept


@dataclass
class ProjectorFaults:
    """Faults a test can inject: a lamp failure (status error, no light reaches the scene), and on the serial
    control port (power, source, status) the next ``serial_timeouts`` commands get no reply and the next
    ``garbled_replies`` an unparsable one, as a real ESC/VP21 line does when it is noisy or unplugged. The
    next ``late_presents`` frames light the scene one refresh later than their present stamp says (a missed
    vertical blank); the display latency itself is ``SimProjector.latency_s``, which a test may change."""

    lamp_error: bool = False
    serial_timeouts: int = 0
    garbled_replies: int = 0
    late_presents: int = (
        0  # the next N frames reach the mirrors one refresh later than stamped (missed vblank)
    )


class SimProjector(ProjectorHooks):
    """A projector on the scene simulator. ``current_image`` is the frame on its HDMI input (read back pixel
    exact); :meth:`emitted_image` is what actually lights the scene (black when off, on the internal source or
    with a lamp fault). Listeners registered with :meth:`add_frame_listener` get the projector's frame sync
    after every :meth:`show` / :meth:`step`, which is how a hardware-triggered camera follows it."""

    def __init__(
        self, config: ProjectorConfig, lamp_hours: float = 0.0, clock: SimClock | None = None
    ) -> None:
        self.config = config
        self.name = config.name
        self.timing = config.timing
        self.clock = clock or SimClock()  # a SimCamera built on this projector replaces it by the world's
        self.frame_period_s = 1.0 / config.timing.refresh_hz
        self.latency_s = (
            float(config.options.get("latency_frames", DEFAULT_LATENCY_FRAMES)) * self.frame_period_s
        )
        self.last_present_s = math.nan
        self.present_count = 0
        self.faults = ProjectorFaults()
        self._connected = False
        self._powered = False
        self._source = ProjectorSource.HDMI
        self._lamp_hours = float(config.options.get("lamp_hours", lamp_hours))
        self._black = np.zeros((config.height_px, config.width_px), dtype=np.uint8)
        self._image = self._black
        self._sequence: list[NDArray[np.uint8]] = []
        self._index = -1
        self._listeners: list[Callable[[float], None]] = []
        self._timeline: list[tuple[float, NDArray[np.uint8]]] = [
            (-math.inf, self._black)
        ]  # (light on, image)

    @property
    def resolution(self) -> tuple[int, int]:
        return (self.config.width_px, self.config.height_px)

    def connect(self) -> None:
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def _require_connection(self) -> None:
        if not self._connected:
            raise DeviceFault(self.name, "not connected; call connect() first")

    def _control(self, command: str) -> None:
        """A command over the serial control port: connected, and any injected line fault."""
        self._require_connection()
        if self.faults.serial_timeouts > 0:
            self.faults.serial_timeouts -= 1
            raise DeviceTimeout(self.name, f"no reply to '{command}' on the serial control port")
        if self.faults.garbled_replies > 0:
            self.faults.garbled_replies -= 1
            raise DeviceProtocolError(self.name, f"garbled reply to '{command}' on the serial control port")

    def set_power(self, on: bool) -> None:
        self._control("PWR")
        self._powered = bool(on)

    def set_source(self, source: ProjectorSource) -> None:
        self._control("SOURCE")
        self._source = ProjectorSource(source)

    def status(self) -> ProjectorStatus:
        self._control("PWR?")
        errors = ("lamp failure: replace the lamp",) if self.faults.lamp_error else ()
        temp = RUNNING_TEMPERATURE_C if self._powered else AMBIENT_TEMPERATURE_C
        return ProjectorStatus(self._powered, self._source, self._lamp_hours, temp, errors)

    def _checked(self, image: NDArray[np.uint8], what: str) -> NDArray[np.uint8]:
        img = np.asarray(image)
        shape = (self.config.height_px, self.config.width_px)
        if img.dtype != np.uint8 or img.shape != shape:
            raise ConfigError(
                f"projector '{self.name}' shows uint8 images of shape {shape} (height, width) pixel-exact; "
                f"{what} is {img.dtype} {img.shape}: generate patterns at the projector resolution"
            )
        out = img.copy()
        out.setflags(write=False)
        return out

    def _present(self, image: NDArray[np.uint8]) -> None:
        """Flip at the next vertical blank (the clock advances to it), stamp it, schedule the light."""
        now = self.clock.now()
        t_present = (math.floor(now / self.frame_period_s + 1e-9) + 1) * self.frame_period_s
        self.clock.advance(t_present - now)
        late = 0.0
        if self.faults.late_presents > 0:
            self.faults.late_presents -= 1
            late = self.frame_period_s
        self._image = image
        self.last_present_s = t_present
        self.present_count += 1
        t_light = t_present + self.latency_s
        keep = [e for e in self._timeline if e[0] <= t_light + late]
        self._timeline = keep + [(t_light + late, image)]
        while len(self._timeline) > 2 and self._timeline[1][0] < now - HISTORY_S:
            self._timeline.pop(0)
        self._notify(t_light)

    def show(self, image: NDArray[np.uint8]) -> None:
        """Present ``image`` at the next vertical blank; returns after the flip (``last_present_s``)."""
        self._require_connection()
        self._present(self._checked(image, "the image"))

    def load_sequence(self, images: Sequence[NDArray[np.uint8]]) -> None:
        self._require_connection()
        if len(images) == 0:
            raise ConfigError(f"projector '{self.name}': a pattern sequence needs at least one image")
        self._sequence = [self._checked(im, f"image {i} of the sequence") for i, im in enumerate(images)]
        self._index = -1

    def step(self) -> int:
        """Show the next image of the sequence; after the last it starts again at 0 (a DLP loop)."""
        self._require_connection()
        if not self._sequence:
            raise DeviceFault(self.name, "step() without a loaded sequence; call load_sequence() first")
        self._index = (self._index + 1) % len(self._sequence)
        self._present(self._sequence[self._index])
        return self._index

    def run_sequence(self, camera: Camera, count: int, timeout_ms: float) -> list[Frame | None]:
        """Pattern mode: flush the camera, present ``count`` patterns of the loaded sequence back to back (one
        per refresh), fetching finished frames between refreshes (the camera has only a few buffers) and
        placing them by their ids from the camera's expected first id (so a lost first frame shows)."""
        self._require_connection()
        if (
            getattr(getattr(camera, "settings", None), "trigger", TriggerMode.HARDWARE)
            is not TriggerMode.HARDWARE
        ):
            raise DeviceFault(
                camera.name, "run_sequence needs the camera in hardware trigger (the projector's trigger out)"
            )
        flush = getattr(camera, "flush", None)
        if flush is not None:
            flush()
        first = expected_frame_id(camera)
        self._index = -1
        received: list[Frame] = []
        for _ in range(count):
            self.step()
            received += grab_ready(camera)
        return frames_by_id(camera, count, timeout_ms, first_id=first, received=received)

    # -------------------------------------------------------------------------------------- simulator side
    @property
    def current_image(self) -> NDArray[np.uint8]:
        """The frame on the HDMI input, pixel-exact (read-only)."""
        return self._image

    def _lit(self) -> bool:
        return (
            self._connected
            and self._powered
            and self._source is ProjectorSource.HDMI
            and not self.faults.lamp_error
        )

    def emitted_image(self) -> NDArray[np.uint8]:
        """What lights the scene now: the frame whose light has arrived, when powered, on HDMI and without a
        fault; else black."""
        return self.emission(self.clock.now(), self.clock.now())[-1][0]

    def emission(self, t0: float, t1: float) -> list[tuple[NDArray[np.uint8], float, float]]:
        """(image, start, end) of every frame that lit the scene during [t0, t1] (s), in order."""
        if not self._lit():
            return [(self._black, t0, t1)]
        out = []
        for i, (t_on, image) in enumerate(self._timeline):
            t_off = self._timeline[i + 1][0] if i + 1 < len(self._timeline) else math.inf
            a, b = max(t0, t_on), min(t1, t_off)
            if b - a > 1e-9 or (t0 == t1 and t_on <= t0 < t_off):  # slivers below 1 ns are float rounding
                out.append((image, a, b))
        return out or [(self._black, t0, t1)]

    def frame_start(self, t: float) -> float:
        """Start of the mirror frame containing ``t`` (frames are on the vblank grid shifted by latency)."""
        T = self.frame_period_s
        return math.floor((t - self.latency_s) / T + 1e-9) * T + self.latency_s

    def add_frame_listener(self, callback: Callable[[float], None]) -> None:
        """Call ``callback(t_light_s)`` at every new frame (the frame-sync output; when its light starts)."""
        self._listeners.append(callback)

    def remove_frame_listener(self, callback: Callable[[float], None]) -> None:
        if callback in self._listeners:
            self._listeners.remove(callback)

    def _notify(self, t_light: float) -> None:
        for callback in list(self._listeners):
            callback(t_light)
