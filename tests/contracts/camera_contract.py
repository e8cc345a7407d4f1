"""Contract tests every Camera implementation must pass (real, simulated, replay).

Use as a mixin: ``class TestMyCamera(CameraContract)`` with a fixture ``camera`` that yields an *unconnected*
device whose software trigger produces a frame. A capability a device lacks (trigger mode, pixel format) is
skipped with pytest.skip when configure() refuses it, so the suite stays implementation-neutral.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from cell.contracts import Camera, CameraSettings, Frame, PixelFormat, TriggerMode
from cell.errors import CellError, DeviceTimeout

_DTYPES = {8: np.uint8, 10: np.uint16, 12: np.uint16}


def _configure_or_skip(camera: Camera, settings: CameraSettings) -> CameraSettings:
    try:
        return camera.configure(settings)
    except CellError as exc:
        pytest.skip(f"{camera.name} does not support {settings}: {exc}")


class CameraContract:
    """What a Camera promises; needs a ``camera`` fixture (unconnected)."""

    timeout_ms = 200.0
    timeout_slack_s = 1.0  # wall-clock allowance over the timeout for the call itself
    refused_settings: tuple[CameraSettings, ...] = ()  # settings the device is documented to refuse

    def test_is_a_camera(self, camera: Camera) -> None:
        assert isinstance(camera, Camera)
        assert isinstance(camera.name, str) and camera.name

    def test_identity_and_resolution(self, camera: Camera) -> None:
        camera.connect()
        try:
            assert isinstance(camera.serial, str) and camera.serial
            assert isinstance(camera.model, str) and camera.model
            w, h = camera.resolution
            assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0
        finally:
            camera.close()

    def test_connect_and_close_are_idempotent(self, camera: Camera) -> None:
        camera.connect()
        camera.connect()
        camera.close()
        camera.close()
        camera.connect()  # and it can come back
        camera.close()

    def test_configure_round_trip(self, camera: Camera) -> None:
        camera.connect()
        try:
            wanted = CameraSettings(
                exposure_ms=7.5, gain_db=3.0, pixel_format=PixelFormat.MONO8, trigger=TriggerMode.SOFTWARE
            )
            got = camera.configure(wanted)
            assert isinstance(got, CameraSettings)
            assert got.exposure_ms == pytest.approx(wanted.exposure_ms, rel=0.05)
            assert got.gain_db == pytest.approx(wanted.gain_db, abs=0.5)
            assert got.pixel_format is wanted.pixel_format and got.trigger is wanted.trigger
            assert camera.configure(got) == got  # what was accepted is accepted unchanged
        finally:
            camera.close()

    @pytest.mark.parametrize("fmt", [PixelFormat.MONO8, PixelFormat.MONO10, PixelFormat.MONO12])
    def test_grab_after_trigger_returns_a_frame(self, camera: Camera, fmt: PixelFormat) -> None:
        camera.connect()
        try:
            got = _configure_or_skip(
                camera, CameraSettings(exposure_ms=5.0, pixel_format=fmt, trigger=TriggerMode.SOFTWARE)
            )
            camera.trigger()
            frame = camera.grab(self.timeout_ms)
            w, h = camera.resolution
            assert isinstance(frame, Frame)
            assert frame.pixels.shape == (h, w)
            assert frame.pixels.dtype == _DTYPES[got.pixel_format.bit_depth]
            assert int(frame.pixels.max()) <= 2**got.pixel_format.bit_depth - 1
            assert isinstance(frame.timestamp_s, float) and np.isfinite(frame.timestamp_s)
            assert isinstance(frame.metadata, dict)
        finally:
            camera.close()

    def test_frame_ids_and_timestamps_increase(self, camera: Camera) -> None:
        camera.connect()
        try:
            camera.configure(CameraSettings(exposure_ms=5.0, trigger=TriggerMode.SOFTWARE))
            frames = []
            for _ in range(3):
                camera.trigger()
                frames.append(camera.grab(self.timeout_ms))
            ids = [f.frame_id for f in frames]
            stamps = [f.timestamp_s for f in frames]
            assert ids == sorted(set(ids))
            assert stamps == sorted(stamps)
        finally:
            camera.close()

    def test_frame_ids_count_every_frame_the_camera_sent(self, camera: Camera) -> None:
        """Ids come from the camera's own count, so consecutive triggers give consecutive ids (a lost frame
        would show as a gap instead of shifting a stack by one pattern)."""
        camera.connect()
        try:
            camera.configure(CameraSettings(exposure_ms=5.0, trigger=TriggerMode.SOFTWARE))
            ids = []
            for _ in range(4):
                camera.trigger()
                ids.append(camera.grab(self.timeout_ms).frame_id)
            assert np.all(np.diff(ids) == 1), ids
        finally:
            camera.close()

    def test_a_refused_setting_names_the_camera(self, camera: Camera) -> None:
        """A mode the camera cannot do (``refused_settings``: a pixel format it lacks, hardware trigger
        without trigger lines) is refused by configure(), before any frame, with an error naming the camera;
        the camera still works afterwards."""
        assert self.refused_settings, "declare refused_settings: what this device's documentation refuses"
        camera.connect()
        try:
            for settings in self.refused_settings:
                with pytest.raises(CellError) as info:
                    camera.configure(settings)
                assert camera.name in str(info.value), info.value
            accepted = camera.configure(CameraSettings(trigger=TriggerMode.SOFTWARE))
            camera.trigger()
            assert camera.grab(self.timeout_ms * 10).pixels.ndim == 2 and accepted.pixel_format
        finally:
            camera.close()

    def test_grab_with_timeout_zero_polls(self, camera: Camera) -> None:
        """grab(0) returns a frame that is waiting or raises DeviceTimeout at once (never waits forever):
        a sequence is fetched while it runs by polling (cell.contracts.grab_ready)."""
        camera.connect()
        try:
            camera.configure(CameraSettings(exposure_ms=5.0, trigger=TriggerMode.SOFTWARE))
            t0 = time.monotonic()
            with pytest.raises(DeviceTimeout):
                camera.grab(0.0)
            assert time.monotonic() - t0 <= self.timeout_slack_s
            camera.trigger()
            assert camera.grab(self.timeout_ms * 10).pixels.ndim == 2
        finally:
            camera.close()

    def test_grab_without_trigger_times_out_in_time(self, camera: Camera) -> None:
        camera.connect()
        try:
            camera.configure(CameraSettings(exposure_ms=5.0, trigger=TriggerMode.SOFTWARE))
            t0 = time.monotonic()
            with pytest.raises(DeviceTimeout) as info:
                camera.grab(self.timeout_ms)
            assert time.monotonic() - t0 <= self.timeout_ms / 1000 + self.timeout_slack_s
            assert info.value.retryable and camera.name in str(info.value)
        finally:
            camera.close()

    def test_free_run_grabs_without_trigger(self, camera: Camera) -> None:
        camera.connect()
        try:
            _configure_or_skip(camera, CameraSettings(exposure_ms=5.0, trigger=TriggerMode.FREE_RUN))
            a = camera.grab(self.timeout_ms)
            b = camera.grab(self.timeout_ms)
            assert b.frame_id > a.frame_id
        finally:
            camera.close()
