"""GenICamCamera through harvesters against the viky.cti GenTL producer of the genicam wheel (no hardware)."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import CameraConfig, load_cell_config
from cell.contracts import CameraSettings, PixelFormat, TriggerMode
from cell.errors import DeviceFault
from drivers.genicam_camera import GenICamCamera, to_numpy, viky_cti
from tests.contracts.camera_contract import CameraContract

pytestmark = [
    pytest.mark.timeout(30),
    pytest.mark.skipif(viky_cti() is None or not viky_cti().is_file(), reason="viky.cti not installed"),
]


def camera_config(**options: object) -> CameraConfig:
    from pathlib import Path

    base = load_cell_config(
        Path(__file__).resolve().parent.parent / "recipes" / "cells" / "sim.yaml"
    ).sensor.camera
    return CameraConfig.model_validate(
        {
            **base.model_dump(),
            "driver": "genicam",
            "serial": "0",
            "width_px": 160,
            "height_px": 120,
            "options": options,
        }
    )


def _viky(**options: object) -> GenICamCamera:
    cam = GenICamCamera(camera_config(**options))
    return cam


class TestGenICamOnViky(CameraContract):
    timeout_ms = 500.0
    refused_settings = (CameraSettings(pixel_format=PixelFormat.MONO10),)  # viky offers Mono8 and colour

    @pytest.fixture
    def camera(self):
        cam = _viky(ignore_missing=["ExposureTime", "Gain"])
        yield cam
        cam.close()


def test_missing_node_is_named() -> None:
    cam = _viky()
    cam.connect()
    try:
        with pytest.raises(DeviceFault, match="ExposureTime is absent"):
            cam.configure(CameraSettings())
    finally:
        cam.close()


def test_unknown_serial_lists_what_is_there() -> None:
    cfg = camera_config()
    cam = GenICamCamera(cfg.model_copy(update={"serial": "NOPE"}))
    with pytest.raises(DeviceFault, match=r"serials seen: \['0', '1', '2'\]"):
        cam.connect()


def test_software_trigger_gives_a_mono8_frame_of_the_node_size() -> None:
    cam = _viky(ignore_missing=["ExposureTime", "Gain"])
    cam.connect()
    try:
        nm = cam._ia.remote_device.node_map
        assert (nm.Width.value, nm.Height.value) == (160, 120) == cam.resolution  # applied from the config
        nm.Width.value, nm.Height.value = 200, 100
        cam.configure(CameraSettings(pixel_format=PixelFormat.MONO8, trigger=TriggerMode.SOFTWARE))
        cam.trigger()
        frame = cam.grab(1000)
        assert frame.pixels.shape == (100, 200) and frame.pixels.dtype == np.uint8
        assert frame.metadata["pixel_format"] == "Mono8"
    finally:
        cam.close()


def test_to_numpy_formats() -> None:
    rgba = np.arange(2 * 3 * 4, dtype=np.uint8)
    img = to_numpy(rgba, 3, 2, "RGBa8")
    assert img.shape == (2, 3, 3) and img[1, 2].tolist() == [20, 21, 22]  # pixel (1,2) = bytes 20..23
    mono12 = np.array([0x0FFF, 1, 2, 3], dtype=np.uint16).view(np.uint8)
    assert to_numpy(mono12, 2, 2, "Mono12").tolist() == [[4095, 1], [2, 3]]


def test_genapi_errors_name_the_camera_and_the_node() -> None:
    cam = _viky(ignore_missing=["ExposureTime", "Gain"])
    cam.connect()
    try:
        with pytest.raises(DeviceFault, match=r"^camera: GenApi node Width: cannot set 100000 on Viky: "):
            cam._write("Width", 100000)  # genicam's OutOfRangeException, wrapped
        with pytest.raises(DeviceFault, match=r"^camera: hardware trigger needs GenApi node TriggerMode"):
            cam.configure(CameraSettings(trigger=TriggerMode.HARDWARE))  # viky has no trigger nodes
    finally:
        cam.close()


def test_frame_ids_come_from_the_producer_and_restart_with_each_acquisition() -> None:
    cam = _viky(ignore_missing=["ExposureTime", "Gain"])
    cam.connect()
    try:
        cam.configure(CameraSettings(trigger=TriggerMode.SOFTWARE))
        frames = []
        for _ in range(3):  # viky has no trigger nodes: each trigger is one acquisition start
            cam.trigger()
            frames.append(cam.grab(1000))
        assert [f.frame_id for f in frames] == [1, 2, 3]
        assert all(isinstance(f.metadata["device_frame_id"], int) for f in frames)
    finally:
        cam.close()
