"""A GenICam camera through harvesters (any GenTL producer: the vendor's .cti, or viky.cti in CI).

Features are set by their standard GenApi node names (SFNC: ExposureTime in us, Gain in dB, PixelFormat,
TriggerSelector/TriggerMode/TriggerSource/TriggerSoftware) after checking the node map. A node the device
lacks is an error naming it, unless ``options.ignore_missing`` lists it (simulated producers): then the value
is not applied, a warning is logged and the returned settings echo the request. Without trigger nodes, a
software trigger is emulated by starting acquisition for one frame (documented latency: one frame period).
"""

from __future__ import annotations

import importlib.util
import logging
import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from cell.config import CameraConfig, Strict, validate
from cell.contracts import CameraSettings, Frame, PixelFormat, TriggerMode
from cell.errors import DeviceFault, DeviceTimeout

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


class GenICamOptions(Strict):
    """``sensor.camera.options`` for ``driver: genicam``."""

    cti: str | None = Field(None, description="GenTL producer file; default: viky.cti of the genicam wheel")
    user_id: str | None = Field(None, description="open by DeviceUserID instead of the config's serial")
    trigger_source: str = Field("Line0", description="input line of the hardware trigger")
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
        self._frames = 0
        self._model = config.model
        self._serial = config.serial

    @property
    def serial(self) -> str:
        return self._serial

    @property
    def model(self) -> str:
        return self._model

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

    def _matches(self, info: Any, key: dict[str, str | None]) -> bool:
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

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Stop acquisition, set nodes, restart per trigger mode; returns the values the nodes report."""
        ia = self._require()
        ia.stop()
        exposure_ms, gain_db = settings.exposure_ms, settings.gain_db
        if (node := self._node("ExposureTime")) is not None:
            node.value = settings.exposure_ms * 1000.0
            exposure_ms = float(node.value) / 1000.0
        if (node := self._node("Gain")) is not None:
            node.value = settings.gain_db
            gain_db = float(node.value)
        fmt = self._node("PixelFormat")
        wanted = _PFNC[settings.pixel_format]
        if fmt is not None:
            if wanted not in fmt.symbolics:
                raise DeviceFault(
                    self.name, f"pixel format {wanted} not offered by {self._model}: {fmt.symbolics}"
                )
            fmt.value = wanted
        if not self._emulated_trigger:
            nm = ia.remote_device.node_map
            if hasattr(nm, "TriggerSelector"):
                nm.TriggerSelector.value = "FrameStart"
            nm.TriggerMode.value = "Off" if settings.trigger is TriggerMode.FREE_RUN else "On"
            if settings.trigger is not TriggerMode.FREE_RUN:
                nm.TriggerSource.value = (
                    "Software" if settings.trigger is TriggerMode.SOFTWARE else self.options.trigger_source
                )
        elif settings.trigger is TriggerMode.HARDWARE:
            raise DeviceFault(self.name, f"{self._model} has no TriggerMode node: no hardware trigger")
        self._settings = CameraSettings(
            exposure_ms=exposure_ms,
            gain_db=gain_db,
            pixel_format=settings.pixel_format,
            trigger=settings.trigger,
        )
        self._armed = False
        if settings.trigger is not TriggerMode.SOFTWARE or not self._emulated_trigger:
            ia.start()
        return self._settings

    def trigger(self) -> None:
        ia = self._require()
        if self._emulated_trigger:
            ia.start()  # acquisition start stands in for the trigger; grab() stops it after one frame
            self._armed = True
        else:
            ia.remote_device.node_map.TriggerSoftware.execute()

    def grab(self, timeout_ms: float) -> Frame:
        """The next frame, copied out of its buffer (which is requeued), or DeviceTimeout after timeout_ms."""
        ia = self._require()
        try:
            from genicam.gentl import TimeoutException
        except ImportError:  # pragma: no cover - genicam comes with harvesters
            TimeoutException = TimeoutError  # noqa: N806
        try:
            with ia.fetch(timeout=timeout_ms / 1000.0) as buffer:
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
                ia.stop()
                self._armed = False
        if self._settings.pixel_format is not PixelFormat.RGB8 and pixels.ndim == 3:
            raise DeviceFault(
                self.name, f"device sent colour data ({c.data_format}) for {self._settings.pixel_format}"
            )
        self._frames += 1  # the device's id restarts with each acquisition start; ours counts every frame
        return Frame(
            pixels=pixels,
            timestamp_s=stamp,
            frame_id=self._frames,
            metadata={
                "pixel_format": c.data_format,
                "device_frame_id": device_frame_id,
                "exposure_ms": self._settings.exposure_ms,
            },
        )
