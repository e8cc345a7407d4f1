"""A GigE Vision / USB3 Vision camera through Aravis (libaravis-0.8 over GObject introspection).

Aravis speaks GVCP/GVSP itself, so no vendor GenTL producer is needed (Debian: ``gir1.2-aravis-0.8``; Python:
PyGObject). Features are set by their GenApi node names, SFNC first and the older GigE names second
(ExposureTime or ExposureTimeAbs in us; Gain in dB, or GainRaw with the datasheet's ``gain_raw_per_db``).

What a structured-light stack needs from a camera, and how this driver makes sure of it:

- every auto feature the camera has (ExposureAuto, GainAuto, BalanceWhiteAuto) is turned off and read back;
- buffers are flushed when a sequence is configured and stale frames are dropped before a software trigger;
- a frame whose packets did not all arrive (buffer status other than success) is never returned: with
  software trigger it is re-captured (the projector still shows the same pattern), otherwise it is an error;
- frame ids are the camera's GVSP block ids, so a frame lost on the wire is a gap, not a shifted stack;
- hardware trigger sets TriggerSource, TriggerActivation and the input line's LineMode; a camera without a
  node a mode needs is an error naming the camera and the node, raised by configure().

Every GenApi/GVCP error (``GLib.GError``) becomes a :class:`DeviceError` naming the camera and the node.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from cell.config import CameraConfig, Strict, validate
from cell.contracts import CameraSettings, Frame, PixelFormat, TriggerMode
from cell.errors import DeviceFault, DeviceTimeout
from drivers.genapi_trigger import auto_features_off, configure_trigger
from drivers.genicam_camera import FrameIdTracker, IncompleteFrame, LostFrames, to_numpy

log = logging.getLogger(__name__)

_PFNC = {
    PixelFormat.MONO8: "Mono8",
    PixelFormat.MONO10: "Mono10",
    PixelFormat.MONO12: "Mono12",
    PixelFormat.RGB8: "RGB8",
}
# PFNC pixel format codes (GigE Vision / GenICam PFNC standard) of the formats above
_PFNC_CODES = {0x01080001: "Mono8", 0x01100003: "Mono10", 0x01100005: "Mono12", 0x02180014: "RGB8"}


def load_aravis() -> Any:
    """The Aravis 0.8 GObject module, or ImportError saying which package is missing."""
    try:
        import gi
    except ImportError as exc:
        raise ImportError("PyGObject is not installed (pip install -e '.[aravis]')", name="gi") from exc
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ValueError, ImportError) as exc:
        raise ImportError(
            f"Aravis 0.8 typelib not found ({exc}); apt-get install gir1.2-aravis-0.8", name="Aravis"
        ) from exc
    return Aravis


class AravisOptions(Strict):
    """``sensor.camera.options`` for ``driver: aravis``."""

    address: str | None = Field(None, description="open by IP address instead of the config's serial")
    trigger_source: str = Field("Line0", description="input line of the hardware trigger")
    trigger_activation: str = Field("RisingEdge", description="edge of the hardware trigger")
    ignore_missing: list[str] = Field(default_factory=list, description="GenApi nodes allowed to be absent")
    gain_raw_per_db: float | None = Field(
        None, gt=0, description="GainRaw steps per dB, from the datasheet, for cameras without a Gain node"
    )
    packet_size: Annotated[int, Field(ge=576, le=65000)] | None = Field(
        None, description="GVSP packet size in bytes (GevSCPSPacketSize); default: negotiated by Aravis"
    )
    recaptures: Annotated[int, Field(ge=0, le=20)] = Field(
        5, description="incomplete frames re-captured per software trigger before giving up"
    )
    buffers: Annotated[int, Field(ge=2, le=64)] = 8


class AravisCamera:
    """Camera contract over Aravis. Frames are copied out of their buffer and the buffer requeued at once."""

    def __init__(self, config: CameraConfig) -> None:
        self.name = config.name
        self._config = config
        self.options = validate(AravisOptions, dict(config.options), f"camera '{config.name}' options")
        self._arv: Any = None
        self._cam: Any = None
        self._dev: Any = None
        self._stream: Any = None
        self._settings = CameraSettings()
        self._ids = FrameIdTracker()
        self._model = config.model
        self._serial = config.serial
        self.incomplete_frames = 0  # frames dropped because packets were missing, since connect()

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
        if self._stream is None:
            return
        self._flush()

    @property
    def resolution(self) -> tuple[int, int]:
        if self._dev is None:
            return (self._config.width_px, self._config.height_px)
        return (self._get("Width", int), self._get("Height", int))

    # ------------------------------------------------------------------------------------- connection
    def connect(self) -> None:
        if self._cam is not None:
            return
        try:
            self._arv = load_aravis()
        except ImportError as exc:
            raise DeviceFault(self.name, str(exc)) from exc
        Aravis, GLib = self._arv, _glib()
        target = self.options.address or self._find_by_serial()
        try:
            self._cam = Aravis.Camera.new(target)
        except GLib.Error as exc:
            raise DeviceFault(self.name, f"cannot open camera {target}: {exc.message}") from exc
        self._dev = self._cam.get_device()
        self._model = self._get("DeviceModelName", str, default=self._model)
        try:
            self._serial = self._cam.get_device_serial_number() or self._serial
        except GLib.Error:  # older GigE devices without DeviceSerialNumber: keep the configured one
            pass
        try:  # the configured image size is the one the calibration is for
            self._set("Width", self._config.width_px)
            self._set("Height", self._config.height_px)
        except DeviceFault:
            self.close()
            raise
        if self.options.packet_size is not None:
            self._set("GevSCPSPacketSize", self.options.packet_size)
        self._ids.reset()
        self.incomplete_frames = 0

    def _find_by_serial(self) -> str:
        Aravis = self._arv
        Aravis.update_device_list()
        seen = {
            Aravis.get_device_serial_nbr(i): Aravis.get_device_id(i) for i in range(Aravis.get_n_devices())
        }
        if self._serial not in seen:
            raise DeviceFault(
                self.name,
                f"no camera with serial {self._serial!r} found by Aravis; serials seen: {sorted(seen)} "
                "(check the cable and the NIC's subnet, or set sensor.camera.options.address)",
            )
        return seen[self._serial]

    def close(self) -> None:
        if self._cam is None:
            return
        try:
            self._stop()
        except DeviceFault as exc:  # a camera that is gone cannot be stopped; closing must go on
            log.warning("%s", exc)
        self._stream = None
        self._dev = None
        self._cam = None  # the GObject reference drop closes the GVCP control channel

    # ------------------------------------------------------------------------------------- GenApi nodes
    def _has(self, node: str) -> bool:
        return self._require().get_feature(node) is not None

    def _require(self) -> Any:
        if self._dev is None:
            raise DeviceFault(self.name, "not connected; call connect() first")
        return self._dev

    def _wrap(self, node: str, action: str, exc: Exception) -> DeviceFault:
        message = getattr(exc, "message", str(exc))
        return DeviceFault(self.name, f"GenApi node {node}: cannot {action} on {self._model}: {message}")

    def _get(self, node: str, kind: type, default: Any = None) -> Any:
        dev = self._require()
        getter = {
            int: dev.get_integer_feature_value,
            float: dev.get_float_feature_value,
            str: dev.get_string_feature_value,
        }[kind]
        try:
            return kind(getter(node))
        except _glib().Error as exc:
            if default is not None:
                return default
            raise self._wrap(node, "read it", exc) from exc

    def _set(self, node: str, value: Any) -> None:
        dev = self._require()
        try:
            if isinstance(value, str):
                dev.set_string_feature_value(node, value)
            elif isinstance(value, int):
                dev.set_integer_feature_value(node, value)
            else:
                dev.set_float_feature_value(node, float(value))
        except _glib().Error as exc:
            raise self._wrap(node, f"set {value!r}", exc) from exc

    def _set_in_range(self, node: str, value: float, unit: str) -> float:
        """Set a numeric node after checking its bounds (Aravis does not), return what it reads back."""
        dev, integer = self._require(), isinstance(value, int)
        try:
            lo, hi = (dev.get_integer_feature_bounds if integer else dev.get_float_feature_bounds)(node)
        except _glib().Error as exc:
            raise self._wrap(node, "read its bounds", exc) from exc
        if not lo <= value <= hi:
            raise DeviceFault(
                self.name, f"GenApi node {node}: {value:g} {unit} is outside {lo:g}..{hi:g} on {self._model}"
            )
        self._set(node, value)
        return self._get(node, int if integer else float)

    def _execute(self, node: str) -> None:
        try:
            self._require().execute_command(node)
        except _glib().Error as exc:
            raise self._wrap(node, "execute it", exc) from exc

    def _entries(self, node: str) -> list[str]:
        try:
            return list(self._require().dup_available_enumeration_feature_values_as_strings(node))
        except _glib().Error as exc:
            raise self._wrap(node, "list its entries", exc) from exc

    def _first(self, *nodes: str, need: str) -> str | None:
        """The first of ``nodes`` the camera has; None if absent but allowed; else an error naming them."""
        for node in nodes:
            if self._has(node):
                return node
        if any(n in self.options.ignore_missing for n in nodes):
            log.warning(
                "%s: GenApi node %s absent; %s not applied (ignore_missing)", self.name, nodes[0], need
            )
            return None
        raise DeviceFault(
            self.name,
            f"GenApi node {' or '.join(nodes)} is absent on {self._model}: {need} cannot be set "
            "(list it in sensor.camera.options.ignore_missing to run without it)",
        )

    def _set_enum(self, node: str, value: str) -> None:
        entries = self._entries(node)
        if value not in entries:
            raise DeviceFault(
                self.name, f"GenApi node {node} of {self._model} has no entry {value!r}; it offers {entries}"
            )
        self._set(node, value)
        if (got := self._get(node, str)) != value:
            raise DeviceFault(self.name, f"GenApi node {node} reads {got!r} after setting {value!r}")

    # ------------------------------------------------------------------------------------- contract
    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Stop acquisition, turn auto features off, set the nodes, flush, restart; returns what the nodes
        report. Raises DeviceFault naming the node when the camera lacks one the settings need."""
        self._require()
        self._stop()
        auto_features_off(self._has, self._set_enum)
        exposure_ms, gain_db = settings.exposure_ms, settings.gain_db
        if node := self._first("ExposureTime", "ExposureTimeAbs", need="the exposure"):
            exposure_ms = self._set_in_range(node, settings.exposure_ms * 1000.0, "us") / 1000.0
        gain_db = self._configure_gain(settings.gain_db)
        if node := self._first("PixelFormat", need="the pixel format"):
            self._set_enum(node, _PFNC[settings.pixel_format])
        self._configure_trigger(settings.trigger)
        self._settings = CameraSettings(exposure_ms, gain_db, settings.pixel_format, settings.trigger)
        self._start()
        return self._settings

    def _configure_gain(self, gain_db: float) -> float:
        if self._has("Gain"):
            return self._set_in_range("Gain", float(gain_db), "dB")
        if self._has("GainRaw") and self.options.gain_raw_per_db:
            raw = self._set_in_range("GainRaw", int(round(gain_db * self.options.gain_raw_per_db)), "steps")
            return raw / self.options.gain_raw_per_db
        if "Gain" in self.options.ignore_missing:
            return gain_db
        hint = (
            " (it has GainRaw: set options.gain_raw_per_db from the datasheet)"
            if self._has("GainRaw")
            else ""
        )
        raise DeviceFault(self.name, f"GenApi node Gain is absent on {self._model}{hint}")

    def _configure_trigger(self, mode: TriggerMode) -> None:
        configure_trigger(
            self.name,
            self._model,
            mode,
            has=self._has,
            set_enum=self._set_enum,
            ignore_missing=self.options.ignore_missing,
            line=self.options.trigger_source,
            activation=self.options.trigger_activation,
        )

    def _start(self) -> None:
        """A fresh stream with empty buffers (nothing of a previous sequence survives), then acquire."""
        Aravis, GLib = self._arv, _glib()
        try:
            self._stream = self._cam.create_stream(None, None)
            payload = self._cam.get_payload()
            for _ in range(self.options.buffers):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            self._cam.start_acquisition()
        except GLib.Error as exc:
            raise self._wrap("AcquisitionStart", "start acquisition", exc) from exc
        self._ids.reset()

    def _stop(self) -> None:
        if self._stream is None:
            return
        try:
            self._cam.stop_acquisition()
        except _glib().Error as exc:
            raise self._wrap("AcquisitionStop", "stop acquisition", exc) from exc
        finally:
            self._stream = None  # dropping the stream frees its buffers

    def _flush(self) -> int:
        """Requeue every frame already waiting (it was not caused by the coming trigger); returns how many."""
        n = 0
        while (buf := self._stream.try_pop_buffer()) is not None:
            complete = buf.get_status() == self._arv.BufferStatus.SUCCESS
            self._ids.observe(buf.get_frame_id() if complete else None)
            self._stream.push_buffer(buf)
            n += 1
        return n

    def trigger(self) -> None:
        self._require()
        if self._stream is None:
            raise DeviceFault(self.name, "not configured; call configure() first")
        if self._settings.trigger is not TriggerMode.SOFTWARE:
            raise DeviceFault(
                self.name, f"trigger() needs software trigger, not {self._settings.trigger.value}"
            )
        if stale := self._flush():
            log.warning("%s: dropped %d stale frame(s) before a software trigger", self.name, stale)
        self._execute("TriggerSoftware")

    def grab(self, timeout_ms: float) -> Frame:
        """The next complete frame. With software trigger an incomplete one is re-captured (up to
        ``options.recaptures`` times); otherwise it raises, as does a gap in the camera's frame ids."""
        if self._stream is None:
            raise DeviceFault(self.name, "not configured; call configure() first")
        for attempt in range(self.options.recaptures + 1):
            try:
                return self._grab_complete(timeout_ms)
            except IncompleteFrame as exc:
                self.incomplete_frames += 1
                if self._settings.trigger is not TriggerMode.SOFTWARE or attempt == self.options.recaptures:
                    raise DeviceTimeout(
                        self.name,
                        f"{exc}; {attempt + 1} incomplete frame(s) in a row: check packet loss on the link "
                        "(GevSCPSPacketSize, inter-packet delay, NIC receive buffers)",
                    ) from exc
                log.warning("%s: %s; re-capturing", self.name, exc)
                self._execute("TriggerSoftware")
        raise AssertionError("unreachable")  # pragma: no cover

    def _grab_complete(self, timeout_ms: float) -> Frame:
        Aravis = self._arv
        buf = self._stream.timeout_pop_buffer(int(timeout_ms * 1000))
        if buf is None:
            raise DeviceTimeout(
                self.name,
                f"no frame within {timeout_ms:g} ms; check the trigger ({self._settings.trigger.value}), "
                "the cable and that the camera is powered",
            )
        try:
            status = buf.get_status()
            block_id = int(buf.get_frame_id())
            if status != Aravis.BufferStatus.SUCCESS:
                # a frame whose leader was lost keeps the id of the buffer's previous use: not an id to trust
                self._ids.observe(None)
                raise IncompleteFrame(
                    f"frame incomplete ({status.value_nick}, block id {block_id} or unknown)"
                )
            try:
                frame_id = self._ids.next(block_id)
            except LostFrames as exc:
                raise DeviceTimeout(self.name, f"{exc}; the sequence must be captured again") from exc
            width, height = int(buf.get_image_width()), int(buf.get_image_height())
            name = _PFNC_CODES.get(int(buf.get_image_pixel_format()), hex(buf.get_image_pixel_format()))
            if name != _PFNC[self._settings.pixel_format]:
                raise DeviceFault(
                    self.name, f"camera sent {name} frames for {self._settings.pixel_format.value}"
                )
            pixels = to_numpy(np.frombuffer(buf.get_data(), np.uint8), width, height, name)
            stamp_ns = int(buf.get_timestamp()) or int(buf.get_system_timestamp())
        finally:
            self._stream.push_buffer(buf)
        return Frame(
            pixels=pixels,
            timestamp_s=stamp_ns * 1e-9,
            frame_id=frame_id,
            metadata={
                "pixel_format": name,
                "device_frame_id": block_id,
                "exposure_ms": self._settings.exposure_ms,
                "gain_db": self._settings.gain_db,
                "incomplete_frames": self.incomplete_frames,
            },
        )


def _glib() -> Any:
    from gi.repository import GLib

    return GLib
