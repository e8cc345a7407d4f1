"""Contract tests every Projector implementation must pass (real, simulated, replay).

Use as a mixin: ``class TestMyProjector(ProjectorContract)`` with a fixture ``projector`` that yields an
*unconnected* device. Pixel-exact checks need a read-back of the shown frame (``current_image``, as the
simulated projector has); they are skipped for devices without one.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.contracts import Projector, ProjectorSource, ProjectorStatus
from cell.errors import CellError


def _readback_or_skip(projector: Projector) -> np.ndarray:
    if not hasattr(projector, "current_image"):
        pytest.skip(f"{type(projector).__name__} cannot read back the shown image")
    return np.asarray(projector.current_image)


def _images(projector: Projector, n: int, seed: int = 0) -> list[np.ndarray]:
    w, h = projector.resolution
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, size=(h, w), dtype=np.uint8) for _ in range(n)]


class ProjectorContract:
    """What a Projector promises; needs a ``projector`` fixture (unconnected)."""

    def test_is_a_projector(self, projector: Projector) -> None:
        assert isinstance(projector, Projector)
        w, h = projector.resolution
        assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0

    def test_connect_and_close_are_idempotent(self, projector: Projector) -> None:
        projector.connect()
        projector.connect()
        projector.close()
        projector.close()
        projector.connect()
        projector.close()

    def test_power_and_source_show_in_status(self, projector: Projector) -> None:
        projector.connect()
        try:
            projector.set_power(True)
            projector.set_source(ProjectorSource.HDMI)
            st = projector.status()
            assert isinstance(st, ProjectorStatus)
            assert st.powered and st.source is ProjectorSource.HDMI
            assert isinstance(st.lamp_hours, float) and st.lamp_hours >= 0
            t = st.temperature_c  # NaN: the protocol has no temperature query (ESC/VP21)
            assert isinstance(t, float) and (math.isnan(t) or -20 < t < 120)
            assert isinstance(st.errors, tuple)
            projector.set_source(ProjectorSource.INTERNAL)
            assert projector.status().source is ProjectorSource.INTERNAL
            projector.set_power(False)
            assert not projector.status().powered and not projector.status().ready
        finally:
            projector.close()

    def test_switch_on_makes_it_ready_and_blank(self, projector: Projector) -> None:
        projector.connect()
        try:
            projector.switch_on()
            assert projector.ready()
            (img,) = _images(projector, 1)
            projector.show(img)
            projector.blank()
            assert not _readback_or_skip(projector).any()
            projector.set_power(False)
            assert not projector.ready()
        finally:
            projector.close()

    def test_show_is_pixel_exact(self, projector: Projector) -> None:
        projector.connect()
        try:
            projector.set_power(True)
            (img,) = _images(projector, 1)
            projector.show(img)
            np.testing.assert_array_equal(_readback_or_skip(projector), img)
        finally:
            projector.close()

    def test_show_refuses_wrong_shape_or_dtype(self, projector: Projector) -> None:
        projector.connect()
        try:
            w, h = projector.resolution
            for bad in (
                np.zeros((h + 1, w), np.uint8),
                np.zeros((w, h), np.uint8) if w != h else None,
                np.zeros((h, w), np.uint16),
                np.zeros((h, w, 3), np.uint8),
            ):
                if bad is None:
                    continue
                with pytest.raises((ValueError, CellError)) as info:
                    projector.show(bad)
                assert str(h) in str(info.value) and str(w) in str(info.value)  # says what it wants
        finally:
            projector.close()

    def test_sequence_steps_in_order(self, projector: Projector) -> None:
        projector.connect()
        try:
            projector.set_power(True)
            first, *seq = _images(projector, 4, seed=1)
            projector.show(first)
            projector.load_sequence(seq)
            readable = hasattr(projector, "current_image")
            if readable:  # loading shows nothing yet
                np.testing.assert_array_equal(projector.current_image, first)
            for i, img in enumerate(seq):
                assert projector.step() == i
                if readable:
                    np.testing.assert_array_equal(projector.current_image, img)
        finally:
            projector.close()
