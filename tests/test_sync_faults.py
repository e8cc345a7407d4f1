"""Fault matrix, synchronisation part: whole inspections on the small simulated cell whose display timing
goes wrong mid-run. Each must end in a defined state with every view measured and the same result as an
undisturbed run (tests/same_result.py).

The cell's latency is calibrated (2 refresh periods + the calibration margin), so the scan waits exactly as
long as the light needs and any change of the world's timing shows in the images.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import trimesh

from cell.config import CellConfig, load_recipe
from cell.contracts import CameraSettings, TriggerMode
from cell.controller import Controller, ControllerSettings
from cell.devices import DeviceBundle, build_devices
from cell.errors import DeviceFault
from cell.inspection import LambertianInspection, inspection_controller
from cell.runs import RunFolder
from tests.box_part import small_cell, write_box_recipe
from tests.same_result import assert_same_result
from tests.test_controller import result_of

T_MS = 1000 / 60.0


def calibrated_cell() -> CellConfig:
    cfg = small_cell()
    cfg.sensor.projector.timing.latency_ms = 2 * T_MS + 0.5  # what `cell calibrate latency` measures here
    return cfg


def make_controller(
    recipe_path: Path, run_dir: Path, trigger: str = "software"
) -> tuple[Controller, DeviceBundle]:
    cfg = calibrated_cell()
    cfg.sensor.camera.trigger = trigger
    recipe = load_recipe(recipe_path)
    nominal = trimesh.load(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())  # in {W}
    devices = build_devices(cfg, part_W=nominal, seed=5)
    job = LambertianInspection(recipe, cfg, nominal)
    job.settings.pictures = False
    job.settings.min_cluster_px = 20
    run = (
        RunFolder.open(run_dir)
        if (run_dir / "journal.jsonl").exists()
        else RunFolder.create(run_dir.parent, "box", name=run_dir.name)
    )
    # the recipe's view budget and feedback iterations, as `cell inspect` sets them (cell/inspection_run.py)
    settings = ControllerSettings(
        retry_delay_s=0.0, view_budget=recipe.plan.view_budget, max_iterations=recipe.plan.max_iterations + 1
    )
    return inspection_controller(devices, job, run, settings), devices


@pytest.fixture(scope="module")
def recipe_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_box_recipe(tmp_path_factory.mktemp("box"))


@pytest.fixture(scope="module")
def reference(recipe_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    run_dir = tmp_path_factory.mktemp("ref") / "run"
    ctl, devices = make_controller(recipe_path, run_dir)
    assert ctl.execute() == "done", ctl.message
    views = len(ctl.checkpoint.views)
    return {"result": result_of(run_dir), "views": views, "presents": devices.projector.present_count}


@pytest.mark.parametrize("fault", ["latency_changed", "mixed_frame", "lost_frame"])
def test_timing_faults_end_in_done_with_every_view_and_the_same_result(
    recipe_path: Path, tmp_path: Path, reference: dict, fault: str
) -> None:
    ctl, devices = make_controller(recipe_path, tmp_path / "run")
    projector, camera = devices.projector, devices.camera
    original = camera.trigger
    triggers = {"n": 0}

    def trigger_with_fault() -> None:
        triggers["n"] += 1
        if triggers["n"] == 40:  # in the second view
            if fault == "latency_changed":  # e.g. the projector switched to a processing mode: +1 frame
                projector.latency_s += projector.frame_period_s
            elif fault == "mixed_frame":  # the next present misses its vblank
                projector.faults.late_presents = 1
            else:
                camera.faults.drop_frames = 1
        original()

    camera.trigger = trigger_with_fault
    assert ctl.execute() == "done", ctl.message
    assert len(ctl.checkpoint.views) == reference["views"]
    journal = ctl.run.journal()
    if fault == "lost_frame":  # software trigger: the grab times out, the view is taken again
        assert [e for e in journal if e["event"] == "error" and e["retryable"]]
    else:  # caught by the pair check inside the view and re-captured there: no error
        assert not [e for e in journal if e["event"] == "error"]
        assert projector.present_count > reference["presents"]
    assert_same_result(result_of(ctl.run.path), reference["result"], fault)


def test_a_hardware_triggered_inspection_gives_the_software_triggered_result(
    recipe_path: Path, tmp_path: Path, reference: dict
) -> None:
    """``sensor.camera.trigger: hardware``: the projector's frame sync exposes the camera, frames are placed
    by their ids; with the latency calibrated the two paths see the same light."""
    ctl, devices = make_controller(recipe_path, tmp_path / "run", trigger="hardware")
    configured = []
    original = devices.camera.configure
    devices.camera.configure = lambda s: configured.append(s.trigger) or original(s)
    assert ctl.execute() == "done", ctl.message
    assert set(configured) == {TriggerMode.HARDWARE}
    assert_same_result(result_of(ctl.run.path), reference["result"], "hardware trigger")


def test_a_camera_without_the_trigger_lines_is_refused_before_the_robot_moves(
    recipe_path: Path, tmp_path: Path
) -> None:
    ctl, devices = make_controller(recipe_path, tmp_path / "run", trigger="hardware")

    def refuse(settings: CameraSettings) -> CameraSettings:
        raise DeviceFault(
            devices.camera.name, "hardware trigger needs GenApi node(s) LineSelector, absent on simulated"
        )

    devices.camera.configure = refuse
    state = ctl.execute()
    assert state in ("paused", "fault") and "LineSelector" in ctl.message
    assert [c["command"] for c in devices.robot.command_log] in ([], ["stop"])  # not even homing
