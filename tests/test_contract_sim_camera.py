"""The camera contract suite on the simulated camera (a small sensor over the simulated table)."""

from __future__ import annotations

import pytest

from fakes.camera import SimCamera
from fakes.sim.testing import small_rig
from tests.contracts.camera_contract import CameraContract


@pytest.fixture
def camera() -> SimCamera:
    rig = small_rig(bit_depth=12)
    return rig.camera


class TestSimCamera(CameraContract):
    pass
