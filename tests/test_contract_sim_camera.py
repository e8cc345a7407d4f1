"""The camera contract suite on the simulated camera (a small sensor over the simulated table)."""

from __future__ import annotations

import pytest

from cell.contracts import CameraSettings, PixelFormat
from fakes.camera import SimCamera
from fakes.sim.testing import small_rig
from tests.contracts.camera_contract import CameraContract


@pytest.fixture
def camera() -> SimCamera:
    rig = small_rig(bit_depth=12)
    return rig.camera


class TestSimCamera(CameraContract):
    # Mono8 and the sensor's native MonoN only (fakes/camera.py)
    refused_settings = (
        CameraSettings(pixel_format=PixelFormat.RGB8),
        CameraSettings(pixel_format=PixelFormat.MONO10),
    )
