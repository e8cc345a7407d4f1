"""The projector contract suite on the simulated projector."""

from __future__ import annotations

import pytest

from fakes.projector import SimProjector
from fakes.sim.testing import small_sensor
from tests.contracts.projector_contract import ProjectorContract


@pytest.fixture
def projector() -> SimProjector:
    return SimProjector(small_sensor().projector)


class TestSimProjector(ProjectorContract):
    pass
