"""Simulated projector and camera behaviour beyond the contract: trigger modes, what reaches the scene,
injected faults, and the simulated cell where moving the robot moves the camera."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cell.config import DEFAULT_CELL, SimConfig, load_cell_config
from cell.contracts import CameraSettings, ProjectorSource, TriggerMode
from cell.errors import DeviceFault, DeviceTimeout
from fakes.sim.testing import small_rig, small_sensor
from fakes.sim_cell import build_sim_cell

QUIET = SimConfig(noise=False)


def _connected_rig(trigger: TriggerMode = TriggerMode.SOFTWARE):
    rig = small_rig(sim=QUIET)
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format="Mono12", trigger=trigger))
    return rig


def _level(rig, value: int) -> np.ndarray:
    return np.full((96, 128), value, np.uint8)


def _show(rig, value: int) -> None:
    """Show a level and wait (simulated time) until its light has reached the scene."""
    rig.projector.show(_level(rig, value))
    rig.projector.clock.sleep(rig.projector.latency_s)


def test_software_frame_shows_the_projector_image_at_trigger_time() -> None:
    rig = _connected_rig()
    _show(rig, 255)
    rig.camera.trigger()
    rig.projector.show(_level(rig, 0))  # changed after the exposure: must not matter
    bright = rig.camera.grab(100)
    rig.projector.clock.sleep(rig.projector.latency_s)
    rig.camera.trigger()
    dark = rig.camera.grab(100)
    lit = rig.renderer.view(rig.T_W_C).lit
    assert bright.pixels[lit].mean() > 5 * dark.pixels[lit].mean()
    np.testing.assert_array_equal(bright.metadata["T_W_C"], rig.T_W_C)
    assert bright.metadata["exposure_ms"] == 10.0 and dark.timestamp_s > bright.timestamp_s


def test_hardware_trigger_gives_one_frame_per_projector_step_in_order() -> None:
    rig = _connected_rig(TriggerMode.HARDWARE)
    levels = [40, 120, 250]
    rig.projector.load_sequence([_level(rig, v) for v in levels])
    with pytest.raises(DeviceTimeout):
        rig.camera.grab(50)  # loading shows nothing, so no frame sync yet
    for _ in levels:
        rig.projector.step()
    lit = rig.renderer.view(rig.T_W_C).lit
    means = [rig.camera.grab(50).pixels[lit].mean() for _ in levels]
    assert means == sorted(means) and means[0] < means[-1] / 3
    with pytest.raises(DeviceTimeout):
        rig.camera.grab(50)


def test_projector_off_or_internal_source_leaves_ambient_light_only() -> None:
    rig = _connected_rig(TriggerMode.FREE_RUN)
    _show(rig, 255)
    on = rig.camera.grab(50).pixels
    rig.projector.set_source(ProjectorSource.INTERNAL)
    internal = rig.camera.grab(50).pixels
    rig.projector.set_source(ProjectorSource.HDMI)
    rig.projector.set_power(False)
    off = rig.camera.grab(50).pixels
    rig.projector.set_power(True)
    rig.projector.show(_level(rig, 0))
    np.testing.assert_array_equal(internal, off)
    assert on.mean() > 5 * off.mean()


def test_injected_faults() -> None:
    rig = _connected_rig()
    _show(rig, 255)
    rig.camera.faults.drop_frames = 1
    rig.camera.trigger()
    with pytest.raises(DeviceTimeout, match="lost"):
        rig.camera.grab(50)
    rig.camera.trigger()
    assert rig.camera.grab(50).frame_id == 1  # frame 0 was exposed and dropped
    rig.camera.faults.grab_timeout = True
    rig.camera.trigger()
    t0 = rig.camera.clock.now()
    with pytest.raises(DeviceTimeout):
        rig.camera.grab(250)
    assert rig.camera.clock.now() - t0 == pytest.approx(0.25)  # the simulated clock waited, not the test
    rig.camera.faults.grab_timeout = False
    rig.camera.grab(50)  # the triggered frame is still there

    rig.projector.faults.lamp_error = True
    st = rig.projector.status()
    assert st.errors and not st.ready
    rig.camera.trigger()
    dark = rig.camera.grab(50).pixels
    rig.projector.faults.lamp_error = False
    rig.camera.trigger()
    assert rig.camera.grab(50).pixels.mean() > 5 * dark.mean()


def test_devices_refuse_use_before_connect_and_wrong_trigger_mode() -> None:
    rig = small_rig()
    with pytest.raises(DeviceFault, match="connect"):
        rig.camera.grab(10)
    with pytest.raises(DeviceFault, match="connect"):
        rig.projector.show(_level(rig, 0))
    rig.camera.connect()
    rig.camera.configure(CameraSettings(trigger=TriggerMode.FREE_RUN))
    with pytest.raises(DeviceFault, match="software"):
        rig.camera.trigger()
    rig.projector.connect()
    with pytest.raises(DeviceFault, match="load_sequence"):
        rig.projector.step()


def test_sim_cell_camera_follows_the_robot() -> None:
    """In the ideal world the camera is exactly where the config's chain puts it (the honest world's
    departures are tested in tests/test_sim_world.py)."""
    cfg = load_cell_config(DEFAULT_CELL)
    cfg = cfg.model_copy(
        update={
            "sensor": small_sensor().model_copy(update={"T_T_C": cfg.sensor.T_T_C}),
            "sim": QUIET,
            "world": "ideal",
        }
    )
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), cfg.sensor.T_T_C.matrix()
    probe = build_sim_cell(cfg, None)
    probe.robot.connect()
    target = probe.robot.tool_pose()
    target[:3, 3] += T_W_B[:3, :3].T @ np.array([0.0, 0.0, -250.0])  # 250 mm lower in the world
    eye = (T_W_B @ target @ T_T_C)[:3, 3]
    assert eye[2] > 400.0
    part = trimesh.creation.box(bounds=[eye - (50.0, 50.0, eye[2]), eye + (50.0, 50.0, 30.0 - eye[2])])
    cell = build_sim_cell(cfg, part, seed=3)
    for dev in (cell.robot, cell.projector, cell.camera):
        dev.connect()
    cell.projector.set_power(True)
    cell.projector.show(np.full((96, 128), 255, np.uint8))
    cell.clock.sleep(cell.projector.latency_s)
    cell.camera.trigger()
    before = cell.camera.grab(100)
    np.testing.assert_allclose(before.metadata["T_W_C"], T_W_B @ cell.robot.tool_pose() @ T_T_C, atol=1e-9)
    cell.robot.move_linear(target, 100.0, 500.0)
    cell.camera.trigger()
    after = cell.camera.grab(100)
    T_W_C = after.metadata["T_W_C"]
    np.testing.assert_allclose(T_W_C[:3, 3] - before.metadata["T_W_C"][:3, 3], (0.0, 0.0, -250.0), atol=1e-6)
    assert after.timestamp_s > before.timestamp_s + 1.0  # the move took simulated time
    gt = cell.renderer.ground_truth(T_W_C)
    on_top = gt.part & (np.abs(gt.points_W[..., 2] - 30.0) < 1e-6)
    assert on_top.sum() > 100  # the box placed under the new camera position is in view, top at z=30
    assert not cell.renderer.ground_truth(before.metadata["T_W_C"]).part[on_top].all()
