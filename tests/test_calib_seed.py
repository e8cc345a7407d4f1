"""A calibration routine on a simulated cell draws its noise from the cell's world, the routine's seed and the
routine's kind together (fakes.sim_cell.noise_seed, passed by cell.calibration.routines.run_routine). With
the routine's seed alone, every world of a seed sweep saw the same landing errors in the kinematics routine,
and the calibrated poses came out biased the same way in all of them (issue 17: the box's +y face 0.1 mm out
in all 30 worlds; docs/uncertainty.md); without the kind, every routine of `cell calibrate all` in one world
started the same camera noise and landing sequence, view k of one routine erring as view k of another."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

import cell.calibration.routines as routines
from cell.calibration.handeye_routines import KinematicsJob
from cell.calibration.procedures import CalibrationJob
from cell.calibration.sensor_routines import IntrinsicsJob, SensorJob
from cell.config import DEFAULT_CELL, CellConfig, load_cell_config
from cell.devices import build_devices
from cell.errors import RoutinePaused
from fakes.sim.testing import small_sensor
from fakes.sim_cell import noise_seed

HONEST = DEFAULT_CELL.parent / "sim_binned_honest.yaml"


def _with_sim_seed(cfg: CellConfig, seed: int) -> CellConfig:
    """The same cell and world (its world.seed is written) with another simulator noise seed."""
    assert isinstance(cfg.world, dict) and cfg.world["seed"] == 1  # the world stays the same drawn world
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": seed})})


def _streams(monkeypatch, tmp_path: Path, jobs: list[CalibrationJob]) -> list[tuple]:
    """The noise stream run_routine builds each job's devices with (seed 1), recorded, nothing run."""
    seen: list[tuple] = []

    def record(cfg: CellConfig, *, stream: tuple = (), **_: object) -> None:
        seen.append(stream)
        raise RuntimeError("devices recorded")

    monkeypatch.setattr(routines, "build_devices", record)
    for i, job in enumerate(jobs):
        with pytest.raises(RuntimeError, match="devices recorded"):
            routines.run_routine(job, tmp_path / f"r{i}", HONEST, seed=1)
    monkeypatch.undo()
    return seen


def _draws(cfg: CellConfig, stream: tuple, views: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The flange's landing errors (mm, against the world's true kinematics) after ``views`` moves, and the
    camera's first noise numbers, on the devices a routine gets with ``stream`` (a routine draws its landings
    move by move, its camera noise from one stream)."""
    devices = build_devices(cfg, stream=stream, with_stage=True)
    sim = devices.sim
    assert sim is not None
    sim.robot.connect()
    q0, out = sim.robot.joints(), []
    for k in range(views):
        sim.robot.move_joint(q0 + np.deg2rad(k + 1) * np.array([1, 0, 0, 0, 0, 1]), 1.0, 2.0)
        out.append(sim.flange_pose()[:3, 3] - sim.world.true_flange(sim.robot.joints())[:3, 3])
    return np.array(out), sim.camera.rng.random(8)


def test_two_worlds_calibrated_with_one_routine_seed_land_their_views_apart(monkeypatch, tmp_path: Path):
    base = load_cell_config(HONEST)
    one, two = _with_sim_seed(base, 1), _with_sim_seed(base, 2)
    streams = _streams(monkeypatch, tmp_path, [KinematicsJob(one), KinematicsJob(two)])
    assert streams == [(1, "robot_kinematics")] * 2  # run_routine hands the routine's seed and kind
    (first, _), (again, _) = _draws(one, streams[0]), _draws(one, streams[0])
    other, _ = _draws(two, streams[1])
    assert np.all(np.linalg.norm(first, axis=1) <= 0.03 + 1e-9)  # the UR5e's repeatability ball
    np.testing.assert_array_equal(first, again)  # the same world and routine seed: reproducible
    assert np.all(np.linalg.norm(first - other, axis=1) > 1e-4)  # another world: every view lands elsewhere
    assert noise_seed(one, stream=(1, "robot_kinematics")) != noise_seed(one, stream=(2, "robot_kinematics"))
    assert noise_seed(one) == 1 and noise_seed(one, 7) == 7  # no stream: the seed itself, as an inspection's


def test_two_routines_of_one_world_draw_their_own_noise(monkeypatch, tmp_path: Path):
    cfg = load_cell_config(HONEST)
    streams = _streams(monkeypatch, tmp_path, [IntrinsicsJob(cfg), KinematicsJob(cfg)])
    assert streams == [(1, "camera_intrinsics"), (1, "robot_kinematics")]
    (land_i, noise_i), (land_k, noise_k) = _draws(cfg, streams[0]), _draws(cfg, streams[1])
    assert np.all(np.linalg.norm(land_i - land_k, axis=1) > 1e-4)  # move k of one is not move k of the other
    assert not np.any(noise_i == noise_k)  # nor is their camera noise


def test_a_resumed_routine_draws_what_an_uninterrupted_one_drew(tmp_path: Path):
    """Every view of a routine restarts the simulated cell's noise from its index (DeviceBundle.begin_view),
    and the landing error of the pose the robot holds from the view it came there for
    (cell.calibration.procedures.arrived_for): the sensor routine's views share one pose while the stage steps
    the board, so a run paused before view 2 comes back from home to it and must land as the uninterrupted
    run's robot did at view 0. The calibrated per-pixel model is then the same to the bit. (Before, the
    resumed run's camera noise restarted where view 0's had: alpha's mean moved by 1 %; with view 2's own
    landing drawn, d's mean moved by 1.6 mm.)"""
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    data["sensor"] = {**small_sensor().model_dump(mode="json"), "T_T_C": data["sensor"]["T_T_C"]}
    cell = tmp_path / "small.yaml"
    cell.write_text(yaml.safe_dump(data))
    cfg = load_cell_config(cell)

    def job() -> SensorJob:
        return SensorJob(cfg, steps=3, step_mm=4.0, points=256)  # the fewest steps it takes

    def pause_at_view_2(controller) -> None:
        if controller.state == "scanning_capturing" and controller.current_view == 2:
            controller.request_pause("test")

    with pytest.raises(RoutinePaused):
        routines.run_routine(job(), tmp_path / "paused", cell, seed=1, on_progress=pause_at_view_2)
    resumed = routines.run_routine(job(), tmp_path / "paused", cell, seed=1)
    whole = routines.run_routine(job(), tmp_path / "whole", cell, seed=1)
    journal = (tmp_path / "paused" / "journal.jsonl").read_text()
    assert '"views_done": 2' in journal  # it resumed at view 2
    assert resumed["summary"] == whole["summary"]
    with np.load(tmp_path / "paused" / "sensor.npz") as a, np.load(tmp_path / "whole" / "sensor.npz") as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a.files)
