"""The device bundle's view hooks (cell.devices.DeviceBundle): nothing on a real cell's drivers; on a
simulated cell, ``end_view`` drops the renderer's pose geometry, and the frames taken after it are the same
bits."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from cell.config import load_cell_config
from cell.contracts import CameraSettings, PixelFormat, TriggerMode
from cell.devices import DeviceBundle, build_devices
from tests.box_part import small_cell

REPO = Path(__file__).resolve().parent.parent


class _Untouchable:
    """A device that fails the test when anything of it is used (an attribute read is a call's start)."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str) -> Any:
        raise AssertionError(f"the {self._name} was used: {attr}")


def test_view_hooks_leave_a_real_cells_drivers_alone() -> None:
    """The lab cell's drivers (constructed, not connected: a call on them would need the hardware) are not
    touched by begin_view or end_view, which have no simulated world to act on."""
    real = build_devices(load_cell_config(REPO / "recipes" / "cells" / "lab.yaml"))
    assert not real.simulated and real.sim is None
    real.begin_view(3)
    real.end_view()
    untouchable = DeviceBundle(
        robot=_Untouchable("robot"),  # type: ignore[arg-type]
        camera=_Untouchable("camera"),  # type: ignore[arg-type]
        projector=_Untouchable("projector"),  # type: ignore[arg-type]
        names=real.names,
    )
    untouchable.begin_view(3, arrived=2)
    untouchable.end_view()
    with pytest.raises(AssertionError, match="the camera was used"):  # the stand-in does catch a use
        untouchable.camera.trigger()


def test_end_view_drops_the_pose_geometry_and_the_frames_after_it_are_the_same_bits(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A simulated cell (noise on) whose camera looks down at a box: the view's frames computed its pose's
    geometry once; ``end_view`` drops it, and the view taken again computes it anew and gives bit-identical
    frames (the noise restarted by ``begin_view``; another view's key gives other frames: not a blank
    test)."""
    cfg = small_cell()
    probe = build_devices(cfg, seed=5)
    probe.robot.connect()
    eye = probe.sim.camera_pose()[:3, 3]  # ideal world, home pose: looking straight down
    box = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    box.apply_translation((eye[0], eye[1], 20.0))
    devices = build_devices(cfg, part_W=box, seed=5)
    devices.bring_up()
    cam = cfg.sensor.camera
    devices.camera.configure(
        CameraSettings(cam.exposure_ms, cam.gain_db, PixelFormat.MONO8, TriggerMode.SOFTWARE)
    )
    renderer = devices.sim.camera.renderer
    computed: list[int] = []
    compute = renderer._compute_view
    monkeypatch.setattr(renderer, "_compute_view", lambda T: computed.append(1) or compute(T))
    p = cfg.sensor.projector
    stripes = np.tile((np.arange(p.width_px) // 8 % 2 * 255).astype(np.uint8), (p.height_px, 1))
    patterns = [np.full_like(stripes, 255), stripes]

    def view(key: int) -> list[np.ndarray]:
        devices.begin_view(key)
        frames = []
        for pattern in patterns:
            devices.projector.show(pattern)
            devices.sim.clock.sleep(devices.projector.latency_s)
            devices.camera.trigger()
            frames.append(devices.camera.grab(1000).pixels)
        return frames

    first = view(0)
    assert len(computed) == 1 and len(renderer._cache) == 1
    assert devices.sim.renderer.ground_truth(devices.sim.camera_pose()).part.mean() > 0.1  # the box in view
    assert first[0].std() > 5 and not np.array_equal(first[0], first[1])
    devices.end_view()
    assert len(renderer._cache) == 0
    again = view(0)
    assert len(computed) == 2  # made anew
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    other = view(1)
    assert len(computed) == 2  # held until the view ends
    assert not any(np.array_equal(a, b) for a, b in zip(first, other, strict=True))
