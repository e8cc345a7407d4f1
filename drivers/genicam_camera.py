"""A GenICam camera through harvesters (any GenTL producer: the vendor's .cti, or viky.cti in CI).

Features are set by their standard GenApi node names (SFNC: ExposureTime in us, Gain in dB, PixelFormat,
TriggerSelector/TriggerMode/TriggerSource/TriggerSoftware) after checking the node map. A node the device
lacks is an error naming it, unless ``options.ignore_missing`` lists it (simulated producers): then the value
is not applied, a warning is logged and the returned settings echo the request. Without trigger nodes, a
software trigger is emulated by starting acquisition for one frame (documented latency: one frame period).

For a structured-light stack: auto features (ExposureAuto, GainAuto, BalanceWhiteAuto) are turned off and
read back; GenApi errors become DeviceFaults naming the camera and the node; buffers are flushed before a
software trigger; frame ids come from the camera (the GenTL buffer's frame id), so a lost frame is a gap that
raises instead of shifting the stack; hardware trigger sets TriggerActivation and the line's LineMode.
"""

from __future__ import annotations

import importlib.util
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from cell.config import CameraConfig, Strict, validate
from cell.contracts import CameraSettings, Frame, PixelFormat, TriggerMode
from cell.errors import DeviceFault, DeviceTimeout
from drivers.genapi_trigger import auto_features_off, configure_trigger

log = logging.getLogger(__name__)


def viky_cti() -> Path | None:
    """The simulated GenTL producer shipped in the genicam wheel (three Viky devices, serials 0, 1, 2)."""
    spec = importlib.util.find_spec("genicam")
    return Path(spec.origin).parent / "viky.cti" if spec and spec.origin else None


# GenICam PFNC names the cell reads, and how their buffers become numpy arrays
_PFNC = {
    PixelFormat.MONO8: "Mono8",
    PixelFormat.MONO10: "Mono10",
    PixelFormat.MONO12: "Mono12",
    PixelFormat.RGB8: "RGB8",
}


# auto features a camera may have; all are turned off so that every frame of a stack has the same response
class IncompleteFrame(Exception):
    """A frame whose data did not all arrive (lost packets); never handed to the pipeline."""


class FrameIdTracker:
    """The camera's frame (block) ids as a frame id that only increases; a gap is frames lost on the way.

    GigE Vision 1.x block ids are 16 bit and wrap after 65535 (to 1; id 0 is reserved, some devices use it),
    so steps are counted modulo 2^16. ``reset`` at each acquisition start: devices may restart their count.
    A dropped frame whose leader was lost has no id (0): it is counted as one frame seen.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._unidentified = 0  # frames seen without an id since the last identified one
        self._count = 0  # frames counted since construction, across resets

    def reset(self) -> None:
        self._last = None
        self._unidentified = 0

    def _step(self, block_id: int) -> int:
        if self._last is None:
            return 1 + self._unidentified
        if block_id > self._last:
            return block_id - self._last
        step = (block_id - self._last) % 65536
        return step - 1 if block_id != 0 and step > 1 else step  # wrapped past the reserved id 0

    @property
    def expected(self) -> int | None:
        """The frame id the next frame will get, once a frame has been seen since the last reset (before
        that the device's next block id is unknown)."""
        return None if self._last is None else self._count + 1 + self._unidentified

    def observe(self, block_id: int | None) -> None:
        """A frame the driver saw but drops (incomplete, stale): it is not a lost one. None or 0: no id."""
        if not block_id:
            self._unidentified += 1
            return
        self._count += self._step(block_id)
        self._last, self._unidentified = block_id, 0

    def next(self, block_id: int) -> int:
        """The frame id of a delivered frame; raises LostFrames when frames went missing before it."""
        step, last, seen = self._step(block_id), self._last, self._unidentified
        self._count += step
        self._last, self._unidentified = block_id, 0
        if last is not None and step != 1 + seen:
            raise LostFrames(
                f"camera frame id jumped from {last} to {block_id}: {step - 1 - seen} frame(s) lost"
            )
        return self._count


class LostFrames(Exception):
    """The camera's frame ids show frames that never reached the host."""


class GenICamOptions(Strict):
    """``sensor.camera.options`` for ``driver: genicam``."""

    cti: str | None = Field(None, description="GenTL producer file; default: viky.cti of the genicam wheel")
    user_id: str | None = Field(None, description="open by DeviceUserID instead of the config's serial")
    trigger_source: str = Field("Line0", description="input line of the hardware trigger")
    trigger_activation: str = Field("RisingEdge", description="edge of the hardware trigger")
    ignore_missing: list[str] = Field(default_factory=list, description="GenApi nodes allowed to be absent")
    buffers: Annotated[int, Field(ge=1, le=64)] = 4


def to_numpy(data: np.ndarray, width: int, height: int, data_format: str) -> np.ndarray:
    """A GenTL buffer component as (H, W) uint8/uint16 or (H, W, 3) uint8. RGBa8 drops alpha."""
    flat = np.asarray(data)
    if data_format in ("Mono8",):
        return flat.reshape(height, width).copy()
    if data_format in ("Mono10", "Mono12", "Mono16"):
        return (
            flat.view(np.uint16).reshape(height, width).copy()
            if flat.dtype != np.uint16
            else flat.reshape(height, width).copy()
        )
    if data_format in ("RGB8", "RGBa8", "BGR8", "BGRa8"):
        ch = 4 if data_format.endswith("a8") else 3
        img = flat.reshape(height, width, ch)[:, :, :3]
        return (img[:, :, ::-1] if data_format.startswith("BGR") else img).copy()
    raise ValueError(f"pixel format {data_format} is not supported by the cell")


class GenICamCamera:
    """Camera contract over harvesters. Frames are copied out and the buffer requeued at once."""

    def __init__(self, config: CameraConfig, *, harvester_pool: dict[str, Any] | None = None) -> None:
        """``harvester_pool``: Harvesters shared by producer file. A GenTL producer initialises once per
        process (a second Harvester on the same .cti lists no device), so cameras opened together share one;
        a shared Harvester is left open on close (its owner resets it)."""
        self.name = config.name
        self._pool = harvester_pool
        self._config = config
        self.options = validate(GenICamOptions, dict(config.options), f"camera '{config.name}' options")
        self._harvester: Any = None
        self._ia: Any = None
        self._settings = CameraSettings()
        self._emulated_trigger = False
        self._armed = False
        self._ids = FrameIdTracker()
        self._model = config.model
        self._serial = config.serial

    @property
    def serial(self) -> str:
        return self._serial

    @property
    def model(self) -> str:
        return self._model

    @property
    def next_frame_id(self) -> int | None:
        """The frame id the next frame will get; None until a frame has come since acquisition start."""
        return self._ids.expected

    def flush(self) -> None:
        """Requeue frames already waiting, so that a sequence starting now gets only its own frames."""
        self._require()
        self._flush()

    @property
    def resolution(self) -> tuple[int, int]:
        if self._ia is None:
            return (self._config.width_px, self._config.height_px)
        nm = self._ia.remote_device.node_map
        return (int(nm.Width.value), int(nm.Height.value))

    def connect(self) -> None:
        if self._ia is not None:
            return
        try:
            from harvesters.core import Harvester
        except ImportError as exc:
            raise DeviceFault(
                self.name, f"harvesters is not installed ({exc}); pip install harvesters"
            ) from exc
        cti = self.options.cti or (str(viky_cti()) if viky_cti() else None)
        if not cti or not Path(cti).is_file():
            raise DeviceFault(self.name, f"GenTL producer {cti!r} not found; set sensor.camera.options.cti")
        if self._pool is not None and cti in self._pool:
            h = self._pool[cti]
        else:
            h = Harvester()
            h.add_file(cti)
            h.update()
            if self._pool is not None:
                self._pool[cti] = h
        key = (
            {"user_defined_name": self.options.user_id}
            if self.options.user_id
            else {"serial_number": self._serial}
        )
        found = [i for i, d in enumerate(h.device_info_list) if self._matches(d, key)]
        if not found:
            seen = [self._info(d, "serial_number") for d in h.device_info_list]
            if self._pool is None:
                h.reset()
            raise DeviceFault(self.name, f"no camera with {key} on {cti}; serials seen: {seen}")
        self._harvester = h
        try:
            self._ia = h.create(found[0])
        except Exception as exc:  # harvesters/GenTL raise their own types, e.g. for a device in use
            raise DeviceFault(self.name, f"cannot open camera {key} on {cti}: {exc}") from exc
        self._ia.num_buffers = self.options.buffers
        self._model = self._info(h.device_info_list[found[0]], "model") or self._model
        nm = self._ia.remote_device.node_map
        try:  # the configured image size is the one the calibration is for
            nm.Width.value, nm.Height.value = self._config.width_px, self._config.height_px
        except Exception as exc:  # GenApi raises OutOfRange/AccessException with the node's limits
            self.close()
            raise DeviceFault(
                self.name,
                f"cannot set Width x Height = {self._config.width_px} x "
                f"{self._config.height_px} on {self._model}: {exc}",
            ) from exc
        self._emulated_trigger = not hasattr(nm, "TriggerMode")
        self._armed = False

    @staticmethod
    def _info(info: Any, field: str) -> str | None:
        try:
            return getattr(info, field)
        except Exception:  # GenTL raises NotAvailableException for fields a producer does not support
            return None

    def _matches(self, info: Any, key: Mapping[str, str | None]) -> bool:
        ((field, value),) = key.items()
        return self._info(info, field) == value

    def close(self) -> None:
        if self._ia is not None:
            self._ia.stop()
            self._ia.destroy()
            self._ia = None
        if self._harvester is not None:
            if self._pool is None:
                self._harvester.reset()
            self._harvester = None

    def _node(self, name: str) -> Any | None:
        nm = self._require().remote_device.node_map
        if hasattr(nm, name):
            return getattr(nm, name)
        if name in self.options.ignore_missing:
            log.warning(
                "%s: GenApi node %s absent; value not applied (allowed by ignore_missing)", self.name, name
            )
            return None
        raise DeviceFault(
            self.name,
            f"GenApi node {name} is absent on {self._model}; this camera cannot set it "
            "(list it in sensor.camera.options.ignore_missing to run without it)",
        )

    def _require(self) -> Any:
        if self._ia is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        return self._ia

    def _has(self, name: str) -> bool:
        return hasattr(self._require().remote_device.node_map, name)

    def _write(self, name: str, value: Any) -> Any:
        """Set a GenApi node and return what it reads back; GenApi errors name the camera and the node."""
        node = getattr(self._require().remote_device.node_map, name)
        try:
            node.value = value
            return node.value
        except Exception as exc:  # genicam raises OutOfRange/AccessException/LogicalError with the limits
            raise DeviceFault(
                self.name, f"GenApi node {name}: cannot set {value!r} on {self._model}: {exc}"
            ) from exc

    def _write_enum(self, name: str, value: str) -> None:
        node = getattr(self._require().remote_device.node_map, name)
        if value not in node.symbolics:
            raise DeviceFault(
                self.name,
                f"GenApi node {name} of {self._model} has no entry {value!r}; it offers {node.symbolics}",
            )
        if (got := self._write(name, value)) != value:
            raise DeviceFault(self.name, f"GenApi node {name} reads {got!r} after setting {value!r}")

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Stop acquisition (which flushes every buffer), turn auto features off, set the nodes, restart per
        trigger mode; returns the values the nodes report. A node the settings need but the camera lacks is
        a DeviceFault naming it."""
        self._require()
        self._stop()
        auto_features_off(self._has, self._write_enum)
        exposure_ms, gain_db = settings.exposure_ms, settings.gain_db
        if self._node("ExposureTime") is not None:
            exposure_ms = float(self._write("ExposureTime", settings.exposure_ms * 1000.0)) / 1000.0
        if self._node("Gain") is not None:
            gain_db = float(self._write("Gain", settings.gain_db))
        if self._node("PixelFormat") is not None:
            self._write_enum("PixelFormat", _PFNC[settings.pixel_format])
        if not self._emulated_trigger:
            self._configure_trigger(settings.trigger)
        elif settings.trigger is TriggerMode.HARDWARE:
            raise DeviceFault(
                self.name, f"hardware trigger needs GenApi node TriggerMode, absent on {self._model}"
            )
        self._settings = CameraSettings(
            exposure_ms=exposure_ms,
            gain_db=gain_db,
            pixel_format=settings.pixel_format,
            trigger=settings.trigger,
        )
        self._armed = False
        if settings.trigger is not TriggerMode.SOFTWARE or not self._emulated_trigger:
            self._start()
        return self._settings

    def _configure_trigger(self, mode: TriggerMode) -> None:
        configure_trigger(
            self.name,
            self._model,
            mode,
            has=self._has,
            set_enum=self._write_enum,
            ignore_missing=self.options.ignore_missing,
            line=self.options.trigger_source,
            activation=self.options.trigger_activation,
        )

    def _start(self) -> None:
        try:
            self._require().start()
        except Exception as exc:  # GenTL/GenApi errors of AcquisitionStart
            raise DeviceFault(
                self.name, f"GenApi node AcquisitionStart: cannot start on {self._model}: {exc}"
            ) from exc
        self._ids.reset()  # devices may restart their frame count with each acquisition

    def _stop(self) -> None:
        try:
            self._require().stop()  # harvesters discards every queued buffer (GenTL ACQ_QUEUE_ALL_DISCARD)
        except Exception as exc:
            raise DeviceFault(
                self.name, f"GenApi node AcquisitionStop: cannot stop on {self._model}: {exc}"
            ) from exc

    def _flush(self) -> int:
        """Requeue frames already waiting (they were not caused by the coming trigger); returns how many."""
        n = 0
        while (buffer := self._require().try_fetch(timeout=1e-4)) is not None:
            self._ids.observe(int(buffer.frame_id))
            buffer.queue()
            n += 1
        return n

    def trigger(self) -> None:
        self._require()
        if self._emulated_trigger:
            self._start()  # acquisition start stands in for the trigger; grab() stops it after one frame
            self._armed = True
            return
        if stale := self._flush():
            log.warning("%s: dropped %d stale frame(s) before a software trigger", self.name, stale)
        node = self._require().remote_device.node_map.TriggerSoftware
        try:
            node.execute()
        except Exception as exc:  # GenApi AccessException when the trigger is not armed
            raise DeviceFault(
                self.name, f"GenApi node TriggerSoftware: cannot execute on {self._model}: {exc}"
            ) from exc

    def grab(self, timeout_ms: float) -> Frame:
        """The next complete frame, copied out of its buffer (which is requeued); DeviceTimeout after
        timeout_ms or when the camera's frame ids show a lost frame (harvesters discards incomplete ones)."""
        ia = self._require()
        try:
            from genicam.gentl import TimeoutException
        except ImportError:  # pragma: no cover - genicam comes with harvesters
            TimeoutException = TimeoutError
        try:
            # harvesters reads timeout 0 as "wait forever": a poll (grab(0), grab_ready) waits 0.1 ms instead
            with ia.fetch(timeout=max(timeout_ms / 1000.0, 1e-4)) as buffer:
                c = buffer.payload.components[0]
                pixels = to_numpy(c.data, c.width, c.height, c.data_format)
                device_frame_id = int(buffer.frame_id)
                try:
                    stamp = float(buffer.timestamp_ns) * 1e-9
                except Exception:  # producers without device timestamps: host clock at arrival
                    stamp = time.time()
        except TimeoutException as exc:
            raise DeviceTimeout(
                self.name,
                f"no frame within {timeout_ms:g} ms; check the trigger "
                f"({self._settings.trigger.value}) and the cable",
            ) from exc
        finally:
            if self._emulated_trigger and self._armed:
                self._stop()
                self._armed = False
        try:
            frame_id = self._ids.next(device_frame_id)
        except LostFrames as exc:
            raise DeviceTimeout(self.name, f"{exc}; the sequence must be captured again") from exc
        if self._settings.pixel_format is not PixelFormat.RGB8 and pixels.ndim == 3:
            raise DeviceFault(
                self.name, f"device sent colour data ({c.data_format}) for {self._settings.pixel_format}"
            )
        return Frame(
            pixels=pixels,
            timestamp_s=stamp,
            frame_id=frame_id,
            metadata={
                "pixel_format": c.data_format,
                "device_frame_id": device_frame_id,
                "exposure_ms": self._settings.exposure_ms,
            },
        )
