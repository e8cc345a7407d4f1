"""Simulated area camera: renders what the simulated projector shows, from the pose the robot is at.

An exposure integrates whatever lit the scene during its window (:meth:`SimProjector.emission`): a trigger
that comes before the projector's light has arrived gives the old pattern or a mix of old and new, as on a
real cell. With a DLP projector (``timing.modulation: dlp``) the window is cut at the mirror frames and a grey
level counts only the bit planes the window covers, so a partial frame distorts grey levels.

Noise: after :attr:`SimCamera.rng` is assigned (``SimCell.reseed`` per view) each frame's noise is drawn from
(that seed, the image on the projector's input, the exposures since it was presented), so an image
re-captured after a re-present has exactly the noise of the first capture of that pattern: a view whose
faulty frames were re-captured gives the same result as an undisturbed one.
"""

from __future__ import annotations

import zlib
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
DLP_BITS = 8  # grey levels by 8 binary-weighted bit planes per frame, least significant first
GAIN_RANGE_DB = (0.0, 48.0)
DEFAULT_BUFFERS = 8  # frame buffers of the driver (Aravis's default; harvesters announces 4 by default)


@dataclass
class CameraFaults:
    """Faults a test can inject: every grab times out; the next ``drop_frames`` exposed frames are lost."""

    grab_timeout: bool = False
    drop_frames: int = 0


class SimCamera:
    """A camera on the scene simulator.

    Software trigger: :meth:`trigger` exposes a frame from now for the exposure time (the clock advances by
    it); :meth:`grab` returns it. Hardware trigger: every projector frame sync starts an exposure when that
    frame's light starts (a sync during an exposure is ignored, as a busy sensor ignores a trigger). Free-run:
    :meth:`grab` exposes a new frame now. Timestamps (exposure start) come from ``clock``, which the projector
    shares; a timed-out grab advances that clock by the timeout instead of waiting. Frame ids count every
    exposure, so a lost frame leaves a gap.

    Buffers: like a real driver the camera holds ``options.buffers`` frames (default 8) from exposure start
    until they are grabbed; an exposure that finds every buffer taken is lost (its id is skipped), so a
    sequence longer than the buffers must be fetched while it runs. A grab waits at most its timeout on the
    shared clock: a frame whose exposure ends later is not returned (``grab(0)`` polls).
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
        projector.clock = self.clock  # one world, one time
        self._rng = rng or np.random.default_rng(renderer.sim.seed)
        self._noise_root: tuple[int, ...] | None = None  # set by assigning rng: per-frame keyed noise
        self.faults = CameraFaults()
        self._connected = False
        self._settings = CameraSettings(
            exposure_ms=config.exposure_ms,
            gain_db=config.gain_db,
            pixel_format=self._native_format(),
            trigger=TriggerMode.SOFTWARE,
        )
        self.buffers = self._buffer_count(config)
        self._queue: deque[Frame] = deque()
        self._pending: deque[tuple[float, int, NDArray[np.float64], tuple[int, int]]] = deque()
        self._busy_until = -np.inf
        self._next_id = 0
        self._seen_present = -1
        self._since_present = 0

    @property
    def rng(self) -> np.random.Generator:
        return self._rng

    @rng.setter
    def rng(self, generator: np.random.Generator) -> None:
        """Restart the noise from ``generator``'s seed, keyed per frame (see the module docstring)."""
        self._rng = generator
        seq = getattr(generator.bit_generator, "seed_seq", None)
        entropy = getattr(seq, "entropy", None)
        root = entropy if isinstance(entropy, list | tuple) else [int(generator.integers(2**63))]
        self._noise_root = tuple(int(v) for v in root)

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

    @staticmethod
    def _buffer_count(config: CameraConfig) -> int:
        value = config.options.get("buffers", DEFAULT_BUFFERS)
        if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= 64:
            raise ConfigError(
                f"camera '{config.name}': options.buffers must be a whole number of frame buffers in 1..64, "
                f"not {value!r}",
                field="sensor.camera.options.buffers",
            )
        return value

    @property
    def next_frame_id(self) -> int:
        """The id the next exposure will carry (frames pending or queued already have theirs)."""
        return self._next_id

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
            self._pending.clear()
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
        self._pending.clear()
        return self._settings

    # ------------------------------------------------------------------------------------------ acquisition
    def _noise_key(self) -> tuple[int, int]:
        """(crc of the image on the projector input, exposures since it was presented)."""
        if self.projector.present_count != self._seen_present:
            self._seen_present = self.projector.present_count
            self._since_present = 0
        else:
            self._since_present += 1
        return (zlib.crc32(np.ascontiguousarray(self.projector.current_image).data), self._since_present)

    def _frame_rng(self, key: tuple[int, int]) -> np.random.Generator:
        if self._noise_root is None:
            return self._rng
        return np.random.default_rng([*self._noise_root, *key])

    def _signal(self, T_W_C: NDArray[np.float64], t0: float, t1: float) -> NDArray[np.float32]:
        """Electrons collected during [t0, t1]: each image that lit the scene for its share of the window; a
        DLP frame cut by the window counts only the bit planes inside it."""
        dlp = self.projector.timing.modulation == "dlp"
        parts: list[tuple[NDArray[np.uint8], float, NDArray[np.float64] | None]] = []  # image, s, plane times
        for image, a, b in self.projector.emission(t0, t1):
            planes = self._plane_times(a, b) if dlp else None
            if parts and parts[-1][0] is image:
                prev = parts[-1]
                merged = None if planes is None or prev[2] is None else prev[2] + planes
                parts[-1] = (image, prev[1] + (b - a), merged)
            else:
                parts.append((image, b - a, planes))
        total: NDArray[np.float32] | None = None
        for image, duration, planes in parts:
            for pattern, seconds in self._light(image, duration, planes):
                sig = self.renderer.signal_e(T_W_C, pattern, seconds * 1e3)
                total = sig if total is None else total + sig
        assert total is not None
        return total

    def _plane_times(self, a: float, b: float) -> NDArray[np.float64]:
        """Seconds of each of the DLP_BITS bit planes inside [a, b] (frames of the projector's grid)."""
        T = self.projector.frame_period_s
        edges = np.concatenate([[0.0], np.cumsum(2.0 ** np.arange(DLP_BITS))]) / (2**DLP_BITS - 1) * T
        out = np.zeros(DLP_BITS)
        f = self.projector.frame_start(a)
        while f < b:
            lo, hi = np.maximum(edges[:-1] + f, a), np.minimum(edges[1:] + f, b)
            out += np.clip(hi - lo, 0.0, None)
            f += T
        return out

    def _light(
        self, image: NDArray[np.uint8], seconds: float, planes: NDArray[np.float64] | None
    ) -> list[tuple[NDArray[np.uint8], float]]:
        """(pattern, seconds) pairs whose rendered sum is the light of ``image`` shown for ``seconds``."""
        if planes is None or seconds <= 0:
            return [(image, seconds)]
        full = planes.sum() * (2.0 ** np.arange(DLP_BITS)) / (2**DLP_BITS - 1)
        binary = bool(np.all((image == 0) | (image == 255)))
        if binary or np.allclose(planes, full, rtol=0, atol=1e-9):
            return [(image, seconds)]  # every plane in full frames, or a level whose planes are all alike
        # The renderer maps 255 to full light and 0 to the black level (which leaks in every plane alike), so
        # a plane is rendered as a binary image for its time; the mirrors' level is the linear (gamma) one.
        level = np.rint(255.0 * (image / 255.0) ** self.projector.config.gamma).astype(np.uint8)
        out = []
        for k in range(DLP_BITS):
            if planes[k] > 0:
                on = ((level >> k) & 1).astype(np.uint8) * np.uint8(255)
                out.append((on, float(planes[k])))
        return out

    def _expose(self, t0: float, T_W_C: NDArray[np.float64], key: tuple[int, int]) -> Frame:
        s = self._settings
        t1 = t0 + s.exposure_ms * 1e-3
        signal = self._signal(T_W_C, t0, t1)
        pixels = self.renderer.sensor_dn(signal, s.gain_db, self._frame_rng(key), s.pixel_format.bit_depth)
        frame = Frame(
            pixels=pixels,
            timestamp_s=t0,
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
        return frame

    def _start(self, t0: float) -> None:
        """An exposure starting at ``t0`` (s): queued to render once its window is over; a lost frame (an
        injected loss, or no free buffer) only takes its id."""
        if self.faults.drop_frames > 0:
            self.faults.drop_frames -= 1
            self._next_id += 1
            return
        if len(self._queue) + len(self._pending) < self.buffers:
            T_W_C = np.asarray(self.pose_source(), dtype=np.float64)
            self._pending.append((t0, self._next_id, T_W_C, self._noise_key()))
        self._next_id += 1  # every buffer taken: the exposure happens, its frame is lost on the way
        self._busy_until = t0 + self._settings.exposure_ms * 1e-3

    def _ends_within(self, timeout_ms: float) -> bool:
        """Whether the oldest pending exposure is over within ``timeout_ms`` from now."""
        t_end = self._pending[0][0] + self._settings.exposure_ms * 1e-3
        return t_end <= self.clock.now() + timeout_ms * 1e-3 + 1e-12

    def _develop(self) -> None:
        """Render the oldest pending exposure (advancing the clock to its end if it is not over yet)."""
        t0, frame_id, T_W_C, key = self._pending.popleft()
        t1 = t0 + self._settings.exposure_ms * 1e-3
        if self.clock.now() < t1:
            self.clock.advance(t1 - self.clock.now())
        saved, self._next_id = self._next_id, frame_id
        self._queue.append(self._expose(t0, T_W_C, key))
        self._next_id = saved

    def _on_projector_frame(self, t_light: float) -> None:
        if self._settings.trigger is TriggerMode.HARDWARE and t_light >= self._busy_until:
            self._start(t_light)

    def trigger(self) -> None:
        self._require_connection()
        if self._settings.trigger is not TriggerMode.SOFTWARE:
            raise DeviceFault(
                self.name,
                f"trigger() needs trigger mode 'software', the camera is in "
                f"'{self._settings.trigger.value}'; configure() it first",
            )
        self._start(self.clock.now())
        self.clock.advance(self._settings.exposure_ms * 1e-3)  # the exposure runs before anything else

    def flush(self) -> None:
        """Drop every queued and pending frame (before a sequence, so that no stale frame is taken)."""
        self._require_connection()
        self._queue.clear()
        self._pending.clear()

    def grab(self, timeout_ms: float) -> Frame:
        self._require_connection()
        if not self.faults.grab_timeout:
            if self._settings.trigger is TriggerMode.FREE_RUN and not self._queue and not self._pending:
                self._start(self.clock.now())
            if not self._queue and self._pending and self._ends_within(timeout_ms):
                self._develop()
            if self._queue:
                return self._queue.popleft()
        self.clock.advance(timeout_ms * 1e-3)
        why = {
            TriggerMode.SOFTWARE: "no software trigger was issued or the frame was lost",
            TriggerMode.HARDWARE: "no projector frame sync arrived or the frame was lost",
            TriggerMode.FREE_RUN: "the frame was lost",
        }[self._settings.trigger]
        raise DeviceTimeout(self.name, f"no frame within {timeout_ms:g} ms: {why}")
