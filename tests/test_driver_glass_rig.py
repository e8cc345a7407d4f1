"""GenICamGlassRig on viky.cti (three simulated GenTL devices, serials 0, 1, 2) with software trigger, and its
marker screen on an offscreen HDMI display. Truth: each camera's configured image size (so frame order is
visible in the shapes), the wall clock for timeouts, and the screen config's dot positions for the image."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.contracts import GlassRig
from cell.errors import ConfigError, DeviceFault, DeviceTimeout
from cell.glass.config import GlassRigConfig, load_glass_rig
from drivers.genicam_camera import viky_cti
from drivers.glass_rig import GenICamGlassRig, GlassRigOptions, marker_image

pytestmark = pytest.mark.timeout(30)
needs_viky = pytest.mark.skipif(
    viky_cti() is None or not viky_cti().is_file(), reason="viky.cti not installed"
)

RIG = Path(__file__).resolve().parent.parent / "recipes" / "glass" / "rig_small.yaml"
SIZES = {"0": (160, 120), "1": (200, 100), "2": (240, 104)}  # (width, height) per viky serial
DUMMY_DISPLAY = {"video_driver": "dummy", "renderer": "software"}


def rig_config(serials: tuple[str, ...] = ("0", "1", "2")) -> GlassRigConfig:
    base = load_glass_rig(RIG)
    cams = []
    for i, serial in enumerate(serials):
        w, h = SIZES[serial]
        cam = base.cameras[i].model_dump()
        cam.update(
            driver="genicam",
            serial=serial,
            width_px=w,
            height_px=h,
            cx_px=(w - 1) / 2,
            cy_px=(h - 1) / 2,
            options={"ignore_missing": ["ExposureTime", "Gain"]},
        )
        cams.append(cam)
    return GlassRigConfig.model_validate({**base.model_dump(), "cameras": cams})


@needs_viky
@pytest.mark.parametrize("serials", [("0", "1", "2"), ("2", "0")])
def test_grab_all_gives_one_frame_per_camera_in_camera_order(serials: tuple[str, ...]) -> None:
    rig = GenICamGlassRig(rig_config(serials), {"trigger": "software"})
    assert isinstance(rig, GlassRig)
    rig.connect()
    try:
        for _ in range(2):
            frames = rig.grab_all(1000)
            assert [f.pixels.shape for f in frames] == [SIZES[s][::-1] for s in serials]
            assert [f.metadata["camera"] for f in frames] == [c.name for c in rig.cameras]
            offsets = [f.metadata["trigger_offset_ms"] for f in frames]
            assert offsets[0] == 0.0 and offsets == sorted(offsets)
            skews = {f.metadata["trigger_skew_ms"] for f in frames}
            assert skews == {offsets[-1]} == {rig.last_trigger_skew_ms}
            assert 0 <= rig.last_trigger_skew_ms < 1000
    finally:
        rig.close()


@needs_viky
def test_a_camera_that_never_delivers_times_out_by_name_and_the_rig_recovers() -> None:
    rig = GenICamGlassRig(rig_config(), {"trigger": "software"})
    rig.connect()
    try:
        broken = rig.cameras[1]
        real_trigger = broken.trigger
        broken.trigger = lambda: None  # its trigger never reaches it (cut line)
        t0 = time.monotonic()
        with pytest.raises(
            DeviceTimeout, match=r"no frame within 300 ms .*\(1 of 3 cameras delivered\)"
        ) as info:
            rig.grab_all(300)
        assert info.value.device == broken.name == "cam1"
        assert time.monotonic() - t0 >= 0.3  # it waited the rig's whole budget for the silent camera
        broken.trigger = real_trigger
        frames = rig.grab_all(1000)  # nothing stale left from the failed trigger
        assert [f.pixels.shape for f in frames] == [SIZES[s][::-1] for s in ("0", "1", "2")]
    finally:
        rig.close()


@needs_viky
def test_hardware_trigger_on_a_camera_without_trigger_nodes_is_a_named_fault() -> None:
    rig = GenICamGlassRig(rig_config(), {"trigger": "hardware", "trigger_master": "cam0"})
    with pytest.raises(DeviceFault, match="hardware trigger needs GenApi node TriggerMode, absent") as info:
        rig.connect()  # cam0 (master) runs on emulated software trigger; cam1 cannot be armed on a line
    assert info.value.device == "cam1"
    rig.close()


def test_options_are_checked() -> None:
    cfg = rig_config()
    with pytest.raises(ConfigError, match="screen_pixel_pitch_mm"):
        GenICamGlassRig(cfg, {"screen": "display"})
    with pytest.raises(ConfigError, match="not one of the cameras"):
        GenICamGlassRig(cfg, {"trigger": "hardware", "trigger_master": "cam9"})
    sim = GlassRigConfig.model_validate(
        {**cfg.model_dump(), "cameras": [{**cfg.cameras[0].model_dump(), "driver": "sim"}]}
    )
    with pytest.raises(ConfigError, match="has driver 'sim'") as info:
        GenICamGlassRig(sim)
    assert info.value.field == "cameras.0.driver"


def test_marker_image_puts_every_dot_where_the_config_says() -> None:
    screen = load_glass_rig(RIG).screen
    pitch = 0.77  # mm per monitor pixel: dot centres fall at arbitrary subpixel positions
    w, h = 1024, 768
    img = marker_image(screen, (w, h), pitch)
    dark = (255 - img.astype(np.float64)) / 255  # coverage of each pixel by a dot
    n, labels = cv2.connectedComponents((img < 255).astype(np.uint8), connectivity=8)
    assert n - 1 == screen.rows * screen.cols
    yy, xx = np.mgrid[0:h, 0:w]
    mass = np.bincount(labels.ravel(), dark.ravel())[1:]
    found = np.column_stack([np.bincount(labels.ravel(), (dark * c).ravel())[1:] / mass for c in (xx, yy)])
    # components are numbered in raster order of their first pixel; sort both by (grid row, x)
    expected = screen.dots_mm() / pitch + [(w - 1) / 2, (h - 1) / 2]
    found = found[np.lexsort((found[:, 0], np.round(found[:, 1] * pitch / screen.pitch_mm)))]
    expected = expected[np.lexsort((expected[:, 0], np.round(expected[:, 1] * pitch / screen.pitch_mm)))]
    # px: centres drawn at 1/16 of the 8x supersampling grid, ~2 px radius discs rasterised on that grid
    np.testing.assert_allclose(found, expected, atol=0.05)
    assert np.abs(found - expected).mean() < 0.01
    area = np.pi * (screen.dot_diameter_mm / 2 / pitch) ** 2
    np.testing.assert_allclose(mass, area, rtol=0.03)  # px^2 of black per dot: the diameter is right
    with pytest.raises(ConfigError, match="monitor has 1024x768"):
        marker_image(screen, (w, h), 0.5)


@needs_viky
def test_screen_on_a_display_shows_the_marker_image() -> None:
    pytest.importorskip("sdl2", reason="pysdl2 + pysdl2-dll not installed: no offscreen display")
    options = GlassRigOptions(screen="display", display=DUMMY_DISPLAY, screen_pixel_pitch_mm=0.8)
    rig = GenICamGlassRig(rig_config(("0",)), options)
    rig.connect()
    try:
        shown = rig._display.current_image
        np.testing.assert_array_equal(shown, marker_image(rig.config.screen, (1024, 768), 0.8))
        np.testing.assert_array_equal(rig.screen.dots_mm, rig.config.screen.dots_mm())
        assert len(rig.grab_all(1000)) == 1
    finally:
        rig.close()
