"""Contract tests every GlassRig implementation must pass (real, simulated, replay).

Use as a mixin: ``class TestMyRig(GlassRigContract)`` with a fixture ``glass_rig`` that yields an
*unconnected* rig able to grab (a pane or board in the simulator, triggerable cameras on the real one). Frame
order is checked against each camera's name where the frames carry ``metadata['camera']``, and always against
the camera's own resolution, so the suite stays implementation-neutral.
"""

from __future__ import annotations

import numpy as np
import pytest

from cell.contracts import Camera, Frame, GlassRig, MarkerScreen
from cell.errors import CellError


class GlassRigContract:
    """What a GlassRig promises; needs a ``glass_rig`` fixture (unconnected)."""

    timeout_ms = 1000.0
    grabs = 2  # grab_all calls in the ordering test: enough to see per-camera timestamps advance

    def test_is_a_glass_rig(self, glass_rig: GlassRig) -> None:
        assert isinstance(glass_rig, GlassRig)
        assert isinstance(glass_rig.name, str) and glass_rig.name

    def test_connect_and_close_are_idempotent(self, glass_rig: GlassRig) -> None:
        glass_rig.connect()
        glass_rig.connect()
        glass_rig.close()
        glass_rig.close()
        glass_rig.connect()  # and it can come back
        glass_rig.close()

    def test_cameras_are_named_and_distinct(self, glass_rig: GlassRig) -> None:
        glass_rig.connect()
        try:
            cams = list(glass_rig.cameras)
            assert cams, "a rig needs at least one camera"
            assert all(isinstance(c, Camera) for c in cams)
            names = [c.name for c in cams]
            assert all(isinstance(n, str) and n for n in names)
            assert len(set(names)) == len(names)
            for c in cams:
                w, h = c.resolution
                assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0
        finally:
            glass_rig.close()

    def test_screen_is_a_marker_screen(self, glass_rig: GlassRig) -> None:
        screen = glass_rig.screen
        assert isinstance(screen, MarkerScreen)
        T = np.asarray(screen.T_W_S)
        assert T.shape == (4, 4) and T.dtype == np.float64
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)  # rigid: orthonormal, right-handed
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
        np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
        dots = np.asarray(screen.dots_mm)
        assert dots.ndim == 2 and dots.shape[1] == 2 and len(dots) > 0 and np.all(np.isfinite(dots))
        assert len(np.unique(dots, axis=0)) == len(dots)  # distinct dot positions
        assert screen.dot_diameter_mm > 0

    def test_grab_all_gives_one_frame_per_camera_in_camera_order(self, glass_rig: GlassRig) -> None:
        glass_rig.connect()
        try:
            cams = list(glass_rig.cameras)
            shapes = [c.resolution[::-1] for c in cams]  # (height, width) of each camera's pixels
            names = [c.name for c in cams]
            stamps = []
            for _ in range(self.grabs):
                frames = glass_rig.grab_all(self.timeout_ms)
                assert isinstance(frames, list) and len(frames) == len(cams)
                assert all(isinstance(f, Frame) for f in frames)
                assert [f.pixels.shape for f in frames] == shapes
                assert all(f.pixels.dtype in (np.uint8, np.uint16) for f in frames)
                tagged = [f.metadata.get("camera") for f in frames]
                if any(t is not None for t in tagged):
                    assert tagged == names
                for f in frames:
                    assert isinstance(f.timestamp_s, float) and np.isfinite(f.timestamp_s)
                stamps.append([f.timestamp_s for f in frames])
            # each camera's clock is its own: timestamps are compared per camera, across grabs
            per_camera = np.array(stamps).T
            assert np.all(np.diff(per_camera, axis=1) >= 0)
        finally:
            glass_rig.close()

    def test_grab_all_before_connect_raises(self, glass_rig: GlassRig) -> None:
        with pytest.raises(CellError):
            glass_rig.grab_all(self.timeout_ms)
