"""Simulated DLP projector: holds the image it shows, which the simulated camera renders onto the scene."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.config import ProjectorConfig
from cell.contracts import ProjectorSource, ProjectorStatus
from cell.errors import ConfigError, DeviceFault, DeviceProtocolError, DeviceTimeout

AMBIENT_TEMPERATURE_C = 25.0
RUNNING_TEMPERATURE_C = 42.0  # a DLP projector's reported temperature once warm


@dataclass
class ProjectorFaults:
    """Faults a test can inject: a lamp failure (status error, no light reaches the scene), and on the serial
    control port (power, source, status) the next ``serial_timeouts`` commands get no reply and the next
    ``garbled_replies`` an unparsable one, as a real ESC/VP21 line does when it is noisy or unplugged."""

    lamp_error: bool = False
    serial_timeouts: int = 0
    garbled_replies: int = 0


class SimProjector:
    """A projector on the scene simulator. ``current_image`` is the frame on its HDMI input (read back pixel
    exact); :meth:`emitted_image` is what actually lights the scene (black when off, on the internal source or
    with a lamp fault). Listeners registered with :meth:`add_frame_listener` get the projector's frame sync
    after every :meth:`show` / :meth:`step`, which is how a hardware-triggered camera follows it."""

    def __init__(self, config: ProjectorConfig, lamp_hours: float = 0.0) -> None:
        self.config = config
        self.name = config.name
        self.faults = ProjectorFaults()
        self._connected = False
        self._powered = False
        self._source = ProjectorSource.HDMI
        self._lamp_hours = float(config.options.get("lamp_hours", lamp_hours))
        self._black = np.zeros((config.height_px, config.width_px), dtype=np.uint8)
        self._image = self._black
        self._sequence: list[NDArray[np.uint8]] = []
        self._index = -1
        self._listeners: list[Callable[[], None]] = []

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

    def show(self, image: NDArray[np.uint8]) -> None:
        self._require_connection()
        self._image = self._checked(image, "the image")
        self._notify()

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
        self._image = self._sequence[self._index]
        self._notify()
        return self._index

    # -------------------------------------------------------------------------------------- simulator side
    @property
    def current_image(self) -> NDArray[np.uint8]:
        """The frame on the HDMI input, pixel-exact (read-only)."""
        return self._image

    def emitted_image(self) -> NDArray[np.uint8]:
        """What lights the scene: the current frame when powered, on HDMI and without a fault; else black."""
        ready = self._connected and self._powered and self._source is ProjectorSource.HDMI
        return self._image if ready and not self.faults.lamp_error else self._black

    def add_frame_listener(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` after every new frame (the projector's frame-sync output)."""
        self._listeners.append(callback)

    def remove_frame_listener(self, callback: Callable[[], None]) -> None:
        if callback in self._listeners:
            self._listeners.remove(callback)

    def _notify(self) -> None:
        for callback in list(self._listeners):
            callback()
