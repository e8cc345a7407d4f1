"""The real back-imaging glass rig: N GenICam cameras triggered together and a marker screen (GlassRig).

Triggering (``options.trigger``):

* ``hardware``: every camera is armed on its trigger input line at connect (acquisition running, waiting);
  one pulse then exposes all of them. The pulse comes from ``trigger_master``'s software trigger (that
  camera runs on software trigger and its output line, e.g. LineSource=ExposureActive, is wired to the
  others' inputs) or, without a master, from an external generator. Skew: the line's propagation (us).
* ``software``: each camera gets its own software trigger, in camera order, as fast as the host can; the
  host-side spread of those triggers is reported as the skew (``last_trigger_skew_ms`` and each frame's
  ``metadata['trigger_skew_ms']``). Fine for a static pane; the fallback for cameras without a trigger line.

The marker screen is either printed (a board, nothing to drive) or shown on a monitor through
:class:`drivers.hdmi_display.HdmiDisplay`: dot ``(x, y)`` mm of the screen plane {S} is drawn at display
pixel ``(x, y) / pitch + ((W - 1) / 2, (H - 1) / 2)``, i.e. {S} has its origin at the display centre, x
along the columns and y along the rows, so the config's ``screen.T_W_S`` must be the monitor's pose measured
that way.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator

from cell.config import Strict, validate
from cell.contracts import Camera, CameraSettings, Frame, MarkerScreen, PixelFormat, TriggerMode
from cell.errors import ConfigError, DeviceError, DeviceTimeout
from cell.glass.config import GlassRigConfig, ScreenConfig
from drivers.genicam_camera import GenICamCamera
from drivers.hdmi_display import HdmiDisplay, HdmiDisplayOptions
from drivers.serial_projector import PatternDisplay

_FORMATS = {8: PixelFormat.MONO8, 10: PixelFormat.MONO10, 12: PixelFormat.MONO12}
_SUBPIXEL_BITS = 4  # cv2.circle draws at 1/16 px: dot centres land where the config puts them
_SUPERSAMPLE = 8  # marker dots: coverage sampled on an 8x8 grid per monitor pixel


class GlassRigOptions(Strict):
    """How the real rig triggers and shows its screen (until GlassRigConfig grows a driver section)."""

    trigger: Literal["software", "hardware"] = "software"
    trigger_master: str | None = Field(
        None, description="hardware: camera whose software trigger drives the shared line; None: external"
    )
    screen: Literal["printed", "display"] = "printed"
    display: HdmiDisplayOptions | None = Field(None, description="screen: display - the monitor to use")
    screen_pixel_pitch_mm: Annotated[float, Field(gt=0.01, lt=5)] | None = Field(
        None, description="screen: display - size of one monitor pixel (mm), measured"
    )
    dot_grey: Annotated[int, Field(ge=0, le=255)] = 0
    background_grey: Annotated[int, Field(ge=0, le=255)] = 255

    @model_validator(mode="after")
    def _display_complete(self) -> GlassRigOptions:
        if self.screen == "display" and self.screen_pixel_pitch_mm is None:
            raise ValueError("screen: display needs screen_pixel_pitch_mm (mm per monitor pixel)")
        if self.trigger_master is not None and self.trigger != "hardware":
            raise ValueError("trigger_master only applies to trigger: hardware")
        return self


def marker_image(
    screen: ScreenConfig, size: tuple[int, int], pitch_mm: float, *, dot: int = 0, background: int = 255
) -> NDArray[np.uint8]:
    """The (H, W) uint8 image of ``screen``'s dots on a monitor of ``size`` (W, H) px, ``pitch_mm`` mm/px.

    ConfigError if a dot would fall off the monitor.
    """
    w, h = size
    centres = screen.dots_mm() / pitch_mm + np.array([(w - 1) / 2, (h - 1) / 2])
    radius = screen.dot_diameter_mm / 2 / pitch_mm
    if (
        centres.min(axis=0)[0] - radius < 0
        or centres.min(axis=0)[1] - radius < 0
        or (centres[:, 0].max() + radius > w - 1 or centres[:, 1].max() + radius > h - 1)
    ):
        raise ConfigError(
            f"the {screen.cols}x{screen.rows} dot grid ({screen.pitch_mm} mm pitch) needs "
            f"{(np.ptp(centres[:, 0]) + 2 * radius):.0f}x{(np.ptp(centres[:, 1]) + 2 * radius):.0f} px at "
            f"{pitch_mm} mm/px but the monitor has {w}x{h}",
            field="screen",
        )
    # Coverage by supersampling: OpenCV's anti-aliased circles come out ~0.3 px too wide, so the dots are
    # drawn hard-edged on a grid _SUPERSAMPLE times finer (centres at 1/16 of it) and area-averaged down.
    k = _SUPERSAMPLE
    cover = np.zeros((h * k, w * k), np.uint8)
    scale = 1 << _SUBPIXEL_BITS
    fixed = np.round(((centres + 0.5) * k - 0.5) * scale).astype(np.int64)
    r = int(round((radius * k - 0.5) * scale))  # cv2 fills whole boundary pixels: half a pixel less
    for cx, cy in fixed:  # one call per dot: OpenCV has no batched circle; a few thousand dots at most
        cv2.circle(cover, (int(cx), int(cy)), r, 255, thickness=-1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
    fraction = cv2.resize(cover, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64) / 255
    return np.round(background + (dot - background) * fraction).astype(np.uint8)


class GenICamGlassRig:
    """GlassRig over GenICam cameras (``cameras[i].driver: genicam``) and a printed or displayed screen."""

    def __init__(
        self,
        config: GlassRigConfig,
        options: GlassRigOptions | dict[str, Any] | None = None,
        *,
        display: PatternDisplay | None = None,
    ) -> None:
        self.name = config.name
        self.config = config
        self.options = (
            options
            if isinstance(options, GlassRigOptions)
            else validate(GlassRigOptions, dict(options or {}), f"glass rig '{config.name}' options")
        )
        for i, cam in enumerate(config.cameras):
            if cam.driver != "genicam":
                raise ConfigError(
                    f"the real glass rig drives GenICam cameras; camera '{cam.name}' has driver "
                    f"'{cam.driver}'",
                    field=f"cameras.{i}.driver",
                )
        names = [c.name for c in config.cameras]
        if self.options.trigger_master is not None and self.options.trigger_master not in names:
            raise ConfigError(
                f"trigger_master '{self.options.trigger_master}' is not one of the cameras {names}",
                field="trigger_master",
            )
        self._harvesters: dict[str, Any] = {}  # producer file -> its one Harvester
        self._cameras = [GenICamCamera(c, harvester_pool=self._harvesters) for c in config.cameras]
        if display is None and self.options.screen == "display":
            display = HdmiDisplay(self.options.display or HdmiDisplayOptions(), name=f"{config.name} screen")
        self._display = display if self.options.screen == "display" else None
        self.last_trigger_skew_ms: float | None = None

    @property
    def cameras(self) -> Sequence[Camera]:
        return self._cameras

    @property
    def screen(self) -> MarkerScreen:
        s = self.config.screen
        return MarkerScreen(s.T_W_S.matrix(), s.dots_mm(), s.dot_diameter_mm)

    def _trigger_mode(self, cam: GenICamCamera) -> TriggerMode:
        if self.options.trigger == "software" or cam.name == self.options.trigger_master:
            return TriggerMode.SOFTWARE
        return TriggerMode.HARDWARE

    def connect(self) -> None:
        """Connect and arm every camera (settings of its config), then show the screen; undone on failure."""
        try:
            for cam, cfg in zip(self._cameras, self.config.cameras):
                cam.connect()
                cam.configure(
                    CameraSettings(
                        exposure_ms=cfg.exposure_ms,
                        gain_db=cfg.gain_db,
                        pixel_format=_FORMATS[cfg.bit_depth],
                        trigger=self._trigger_mode(cam),
                    )
                )
            if self._display is not None:
                self._display.open()
                assert self.options.screen_pixel_pitch_mm is not None  # the options validator ensures it
                self._display.show(
                    marker_image(
                        self.config.screen,
                        self._display.size,
                        self.options.screen_pixel_pitch_mm,
                        dot=self.options.dot_grey,
                        background=self.options.background_grey,
                    )
                )
        except (DeviceError, ConfigError):
            self.close()
            raise

    def close(self) -> None:
        for cam in self._cameras:
            cam.close()
        for h in self._harvesters.values():
            h.reset()
        self._harvesters.clear()
        if self._display is not None:
            self._display.close()

    def _fire(self) -> dict[str, float]:
        """Issue the trigger(s); per camera, the host time offset (ms) of its trigger from the first."""
        if self.options.trigger == "hardware":
            self.last_trigger_skew_ms = None  # one electrical pulse: the host cannot see the skew
            master = next((c for c in self._cameras if c.name == self.options.trigger_master), None)
            if master is not None:
                master.trigger()
            return {}
        stamps = []
        for cam in self._cameras:
            stamps.append(time.perf_counter())
            cam.trigger()
        offsets = {c.name: (t - stamps[0]) * 1e3 for c, t in zip(self._cameras, stamps)}
        self.last_trigger_skew_ms = offsets[self._cameras[-1].name]
        return offsets

    def grab_all(self, timeout_ms: float) -> list[Frame]:
        """Trigger every camera together; one frame per camera in camera order, all within ``timeout_ms``.

        A camera that delivers nothing in time raises DeviceTimeout naming it; the frames the later cameras
        may still deliver for this trigger are drained so that the next call starts clean.
        """
        offsets = self._fire()
        deadline = time.monotonic() + timeout_ms / 1000.0
        frames: list[Frame] = []
        for k, cam in enumerate(self._cameras):
            left_ms = max((deadline - time.monotonic()) * 1000.0, 1.0)
            try:
                frame = cam.grab(left_ms)
            except DeviceTimeout as exc:
                self._drain(self._cameras[k + 1 :])
                raise DeviceTimeout(
                    cam.name,
                    f"no frame within {timeout_ms:g} ms of the rig's {self.options.trigger} trigger "
                    f"({k} of {len(self._cameras)} cameras delivered): {exc}",
                ) from exc
            meta: dict[str, Any] = {"camera": cam.name, "trigger": self.options.trigger}
            if offsets:
                meta |= {"trigger_offset_ms": offsets[cam.name], "trigger_skew_ms": self.last_trigger_skew_ms}
            frames.append(dataclasses.replace(frame, metadata={**frame.metadata, **meta}))
        return frames

    @staticmethod
    def _drain(cameras: Sequence[GenICamCamera], timeout_ms: float = 50.0) -> None:
        for cam in cameras:
            try:
                cam.grab(timeout_ms)
            except DeviceTimeout:
                pass
