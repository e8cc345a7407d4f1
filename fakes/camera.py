"""Simulated area camera: renders what the simulated projector shows, from the pose the robot is at."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.config import CameraConfig
from cell.contracts import CameraSettings, Frame, PixelFormat, TriggerMode
from cell.errors import ConfigError, DeviceFault, DeviceTimeout
from fakes.clock import SimClock
from fakes.projector import SimProjector
from fakes.sim.render import SceneRenderer

EXPOSURE_STEP_MS = 0.001  # the sensor sets exposure in 1 us steps
GAIN_STEP_DB = 0.1
EXPOSURE_RANGE_MS = (0.01, 10000.0)
GAIN_RANGE_DB = (0.0, 48.0)
MAX_QUEUED_FRAMES = 64  # frames beyond this are dropped, like a driver's full buffer pool


@dataclass
class CameraFaults:
    """Faults a test can inject: every grab times out; the next ``drop_frames`` exposed frames are lost."""

    grab_timeout: bool = False
    drop_frames: int = 0


class SimCamera:
    """A camera on the scene simulator.

    Software trigger: :meth:`trigger` exposes a frame (the projector's image at that instant); :meth:`grab`
    returns it. Hardware trigger: every projector frame sync exposes one. Free-run: :meth:`grab` exposes a new
    frame now. Timestamps come from ``clock`` (a :class:`SimClock` by default, so nothing sleeps); a timed-out
    grab advances that clock by the timeout instead of waiting.
    """

    def __init__(
        self,
        config: CameraConfig,
        renderer: SceneRenderer,
        projector: SimProjector,
        pose_source: Callable[[], NDArray[np.float64]],
        clock: SimClock | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.config = config
        self.name = config.name
        self.renderer = renderer
        self.projector = projector
        self.pose_source = pose_source
        self.clock = clock or SimClock()
        self.rng = rng or np.random.default_rng(renderer.sim.seed)
        self.faults = CameraFaults()
        self._connected = False
        self._settings = CameraSettings(
            exposure_ms=config.exposure_ms,
            gain_db=config.gain_db,
            pixel_format=self._native_format(),
            trigger=TriggerMode.SOFTWARE,
        )
        self._queue: deque[Frame] = deque()
        self._next_id = 0

    # ------------------------------------------------------------------------------------------ identity
    @property
    def serial(self) -> str:
        return self.config.serial

    @property
    def model(self) -> str:
        return self.config.model

    @property
    def resolution(self) -> tuple[int, int]:
        return (self.config.width_px, self.config.height_px)

    @property
    def settings(self) -> CameraSettings:
        return self._settings

    def _native_format(self) -> PixelFormat:
        return PixelFormat(f"Mono{self.config.bit_depth}")

    # ------------------------------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        if not self._connected:
            self._connected = True
            self.projector.add_frame_listener(self._on_projector_frame)

    def close(self) -> None:
        if self._connected:
            self.projector.remove_frame_listener(self._on_projector_frame)
            self._queue.clear()
            self._connected = False

    def _require_connection(self) -> None:
        if not self._connected:
            raise DeviceFault(self.name, "not connected; call connect() first")

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings: exposure rounded to 1 us and clipped to the sensor range, gain to 0.1 dB. Pixel
        formats: Mono8 and the sensor's native MonoN; anything else is a ConfigError."""
        self._require_connection()
        fmt = PixelFormat(settings.pixel_format)
        if fmt not in (PixelFormat.MONO8, self._native_format()):
            raise ConfigError(
                f"camera '{self.name}' supports Mono8 and {self._native_format().value}, not {fmt.value}",
                field="pixel_format",
            )
        exposure = float(
            np.clip(round(settings.exposure_ms / EXPOSURE_STEP_MS) * EXPOSURE_STEP_MS, *EXPOSURE_RANGE_MS)
        )
        gain = float(np.clip(round(settings.gain_db / GAIN_STEP_DB) * GAIN_STEP_DB, *GAIN_RANGE_DB))
        self._settings = CameraSettings(exposure, gain, fmt, TriggerMode(settings.trigger))
        self._queue.clear()
        return self._settings

    # ------------------------------------------------------------------------------------------ acquisition
    def _expose(self) -> Frame:
        s = self._settings
        T_W_C = np.asarray(self.pose_source(), dtype=np.float64)
        pattern = self.projector.emitted_image()
        pixels = self.renderer.render(
            T_W_C, pattern, s.exposure_ms, s.gain_db, self.rng, bit_depth=s.pixel_format.bit_depth
        )
        frame = Frame(
            pixels=pixels,
            timestamp_s=self.clock.now(),
            frame_id=self._next_id,
            metadata={
                "exposure_ms": s.exposure_ms,
                "gain_db": s.gain_db,
                "pixel_format": s.pixel_format.value,
                "trigger": s.trigger.value,
                "T_W_C": T_W_C.copy(),
                "camera": self.name,
                "serial": self.serial,
            },
        )
        self._next_id += 1
        self.clock.advance(s.exposure_ms * 1e-3)
        return frame

    def _enqueue(self) -> None:
        frame = self._expose()
        if self.faults.drop_frames > 0:
            self.faults.drop_frames -= 1
            return
        if len(self._queue) < MAX_QUEUED_FRAMES:
            self._queue.append(frame)

    def _on_projector_frame(self) -> None:
        if self._settings.trigger is TriggerMode.HARDWARE:
            self._enqueue()

    def trigger(self) -> None:
        self._require_connection()
        if self._settings.trigger is not TriggerMode.SOFTWARE:
            raise DeviceFault(
                self.name,
                f"trigger() needs trigger mode 'software', the camera is in "
                f"'{self._settings.trigger.value}'; configure() it first",
            )
        self._enqueue()

    def grab(self, timeout_ms: float) -> Frame:
        self._require_connection()
        if not self.faults.grab_timeout:
            if self._settings.trigger is TriggerMode.FREE_RUN and not self._queue:
                self._enqueue()
            if self._queue:
                return self._queue.popleft()
        self.clock.advance(timeout_ms * 1e-3)
        why = {
            TriggerMode.SOFTWARE: "no software trigger was issued or the frame was lost",
            TriggerMode.HARDWARE: "no projector frame sync arrived or the frame was lost",
            TriggerMode.FREE_RUN: "the frame was lost",
        }[self._settings.trigger]
        raise DeviceTimeout(self.name, f"no frame within {timeout_ms:g} ms: {why}")
