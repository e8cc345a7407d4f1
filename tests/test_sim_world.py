"""The simulated world differs from the cell config as its ``world:`` section says (fakes/sim/world.py):
sizes, the robot reporting nominal kinematics while the flange follows the true ones, the part off its
fixture, the surface microstructure, and `world: ideal` as the exact model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from cell.config import DEFAULT_CELL, CellConfig, SimConfig, load_cell_config
from cell.contracts import CameraSettings
from cell.errors import ConfigError
from cell.geometry import invert
from cell.planning.kinematics import UR5E
from fakes.sim.testing import small_sensor
from fakes.sim.world import IDEAL, build_world, schema_page, world_config
from fakes.sim_cell import build_sim_cell

REPO = Path(__file__).resolve().parent.parent
QUIET = SimConfig(noise=False)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))


def _small(world: object) -> CellConfig:
    """The default cell with the 160x120 test sensor (fast renders), noise off, and ``world``."""
    cfg = load_cell_config(DEFAULT_CELL)
    sensor = small_sensor(bit_depth=8).model_copy(update={"T_T_C": cfg.sensor.T_T_C})
    return cfg.model_copy(update={"sensor": sensor, "sim": QUIET, "world": world})


def test_default_cell_world_has_the_stated_sizes() -> None:
    cfg = load_cell_config(DEFAULT_CELL)
    w = build_world(cfg)
    wc = w.config
    assert wc == world_config(None).model_copy(update={"seed": 1})  # sim.yaml writes out the defaults
    E = invert(cfg.sensor.T_T_C.matrix()) @ w.sensor.T_T_C.matrix()
    assert np.linalg.norm(E[:3, 3]) == pytest.approx(1.5, abs=1e-9)
    assert _angle_deg(E[:3, :3]) == pytest.approx(0.4, abs=1e-9)
    E = invert(cfg.sensor.projector.T_C_P.matrix()) @ w.sensor.projector.T_C_P.matrix()
    assert np.linalg.norm(E[:3, 3]) == pytest.approx(0.3, abs=1e-9)
    assert _angle_deg(E[:3, :3]) == pytest.approx(0.05, abs=1e-9)
    for true, nominal in ((w.sensor.camera, cfg.sensor.camera), (w.sensor.projector, cfg.sensor.projector)):
        assert abs(true.fx_px / nominal.fx_px - 1) == pytest.approx(0.005, abs=1e-12)
        assert true.fy_px / nominal.fy_px == pytest.approx(true.fx_px / nominal.fx_px, abs=1e-12)
        assert np.hypot(true.cx_px - nominal.cx_px, true.cy_px - nominal.cy_px) == pytest.approx(3.0)
    np.testing.assert_allclose(
        w.sensor.camera.distortion.as_array() - cfg.sensor.camera.distortion.as_array(),
        [0.01, -0.02, 1e-4, -1e-4, 0.0],
        atol=1e-12,
    )
    assert w.projector_distortion.tolist() == [-0.02, 0.01, 0.0, 0.0, 0.0]
    dl = np.abs(np.r_[w.kinematics.dh.d, w.kinematics.dh.a] - np.r_[UR5E.dh.d, UR5E.dh.a])
    assert 0.05 < dl.max() < 1.0 and np.count_nonzero(dl) == 6  # six non-zero DH lengths, each ~0.2 mm off
    assert 0.002 < np.degrees(np.abs(w.joint_zero_rad)).max() < 0.1
    assert np.linalg.norm(w.placement[:3, 3]) == pytest.approx(1.0) and w.placement[2, 3] == 0.0
    assert _angle_deg(w.placement[:3, :3]) == pytest.approx(0.5)
    assert build_world(cfg.model_copy(update={"world": {"seed": 2}})).sensor != w.sensor  # seeded


def test_ideal_world_is_exactly_the_config() -> None:
    cfg = load_cell_config(REPO / "recipes" / "cells" / "sim_binned.yaml")
    assert cfg.world == "ideal"
    w = build_world(cfg)
    assert w.ideal and w.config == IDEAL
    assert w.sensor == cfg.sensor
    q = np.deg2rad(cfg.robot.home_joints_deg)
    assert np.array_equal(w.true_flange(q), UR5E.fk(q))
    assert np.array_equal(w.placement, np.eye(4))
    assert np.array_equal(w.landing_error(np.random.default_rng(0)), np.eye(4))


def test_ideal_base_zeroes_every_error_not_written() -> None:
    wc = world_config({"base": "ideal", "placement": {"translation_mm": 2.0}})
    assert wc.placement.translation_mm == 2.0 and wc.placement.rotation_deg == 0.0
    assert wc.model_copy(update={"placement": IDEAL.placement}) == IDEAL
    assert world_config({"placement": {"translation_mm": 2.0}}).hand_eye.translation_mm == 1.5


def test_robot_reports_nominal_kinematics_while_the_flange_follows_the_world() -> None:
    cfg = _small(None)  # absent world: the realistic defaults
    cell = build_sim_cell(cfg, None)
    for dev in (cell.robot, cell.projector, cell.camera):
        dev.connect()
    world = cell.world
    target = cell.robot.tool_pose()
    target[:3, 3] += (30.0, -20.0, -50.0)
    poses = []
    for _ in range(3):  # there and back, twice: the robot reports the same pose, the world differs
        cell.robot.move_linear(target, 100.0, 500.0)
        assert np.array_equal(cell.robot.tool_pose(), UR5E.fk(cell.robot.joints()))  # what a UR reports
        np.testing.assert_allclose(cell.robot.tool_pose(), target, atol=1e-6)
        flange = cell.flange_pose()
        true = world.true_flange(cell.robot.joints())
        assert np.linalg.norm(flange[:3, 3] - true[:3, 3]) <= 0.03 + 1e-12  # landing: repeatability ball
        kin_error = np.linalg.norm(true[:3, 3] - target[:3, 3])
        assert 0.05 < kin_error < 3.0  # link lengths ~0.2 mm and joint zeros ~0.02 deg over a ~1 m arm
        cell.camera.configure(CameraSettings(exposure_ms=10.0))
        cell.camera.trigger()
        T_W_C = cell.camera.grab(100).metadata["T_W_C"]
        np.testing.assert_allclose(
            T_W_C, cfg.robot.T_W_B.matrix() @ flange @ world.sensor.T_T_C.matrix(), atol=1e-9
        )
        poses.append(flange)
        cell.robot.move_linear(UR5E.fk(np.deg2rad(cfg.robot.home_joints_deg)), 100.0, 500.0)
    spread = max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a in poses for b in poses)
    assert 0 < spread <= 0.06  # every arrival lands elsewhere within +-0.03 mm
    cell.robot.move_linear(target, 100.0, 500.0)
    cell.reseed(4)
    first = cell.camera_pose()
    cell.reseed(4)
    assert np.array_equal(cell.camera_pose(), first)  # a resumed view is where the uninterrupted one was


def test_a_held_pose_keeps_its_landing_error() -> None:
    """A robot that holds its pose does not land again: not on a move to the joints it stands at, exactly or
    to round-off (a calibration routine's joint move to its pose while the stage moves the board), nor at the
    next view's reseed. A resumed run that names the view it came for draws that landing again; a real move
    re-lands."""
    cfg = _small(None)  # the realistic defaults: +-0.03 mm repeatability

    def arrive(cell) -> np.ndarray:
        cell.robot.connect()
        target = cell.robot.tool_pose()
        target[:3, 3] += (30.0, -20.0, -50.0)
        cell.robot.move_linear(target, 100.0, 500.0)
        return target

    cell = build_sim_cell(cfg, None)
    target = arrive(cell)
    landed = cell.flange_pose()
    assert not np.array_equal(landed, cell.world.true_flange(cell.robot.joints()))  # it landed off
    cell.robot.move_joint(cell.robot.joints(), 1.0, 2.0)  # to where it stands
    assert np.array_equal(cell.flange_pose(), landed)
    cell.reseed(5)  # the view it came for: its landing drawn from the view's key
    at_5 = cell.flange_pose()
    cell.robot.move_joint(cell.robot.joints(), 1.0, 2.0)
    cell.reseed(6)  # the next view, held
    assert np.array_equal(cell.flange_pose(), at_5)
    resumed = build_sim_cell(cfg, None)  # a run resumed at view 6 comes from home
    arrive(resumed)
    resumed.reseed(6, arrived=(5,))
    assert np.array_equal(resumed.flange_pose(), at_5)
    cell.robot.move_joint(cell.robot.joints() + 1e-12, 1.0, 2.0)  # to it by an IK solution's round-off
    assert cell.robot.command_log[-1]["duration_s"] > 0.0  # it takes time, but goes nowhere: no new landing
    np.testing.assert_allclose(cell.flange_pose(), at_5, rtol=0.0, atol=1e-6)  # a new one: up to 0.03 mm
    cell.robot.move_linear(UR5E.fk(np.deg2rad(cfg.robot.home_joints_deg)), 100.0, 500.0)
    cell.robot.move_linear(target, 100.0, 500.0)  # away and back: a new landing
    cell.reseed(7)
    assert np.linalg.norm(cell.flange_pose()[:3, 3] - at_5[:3, 3]) > 1e-6


def test_part_sits_off_its_fixture_by_the_placement_error() -> None:
    box = trimesh.creation.box(bounds=[(-60.0, -40.0, 0.0), (60.0, 40.0, 30.0)])
    box.apply_translation((100.0, 50.0, 0.0))
    cell = build_sim_cell(_small(None), box)
    T = cell.T_place_W
    centre = np.array([100.0, 50.0, 0.0])
    assert np.linalg.norm(T[:3, :3] @ centre + T[:3, 3] - centre) == pytest.approx(1.0)  # 1 mm at its centre
    assert _angle_deg(T[:3, :3]) == pytest.approx(0.5) and T[2, 3] == pytest.approx(0.0)
    placed = cell.scene.vertices[4:]  # the table's 4 corners come first
    np.testing.assert_allclose(placed, box.copy().apply_transform(T).vertices, atol=1e-9)
    assert placed[:, 2].min() == pytest.approx(0.0, abs=1e-9)  # still resting on the table
    ideal = build_sim_cell(_small("ideal"), box)
    np.testing.assert_allclose(ideal.scene.vertices[4:], box.vertices, atol=0)


def test_surface_microstructure_raises_the_table_by_the_material_roughness() -> None:
    honest, ideal = build_sim_cell(_small(None), None), build_sim_cell(_small("ideal"), None)
    T_W_C = np.eye(4)
    T_W_C[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down from 400 mm
    T_W_C[2, 3] = 400.0
    z_ideal = ideal.renderer.ground_truth(T_W_C).points_W[..., 2]
    z_honest = honest.renderer.ground_truth(T_W_C).points_W[..., 2]
    assert np.abs(z_ideal).max() < 1e-9
    roughness_mm = honest.config.sim.table_material.roughness_um * 1e-3
    assert np.std(z_honest) == pytest.approx(roughness_mm, rel=0.35)
    assert np.abs(z_honest).max() < 6 * roughness_mm


def test_projector_lens_distortion_moves_the_projector_coordinates() -> None:
    honest = build_sim_cell(_small({"projector_distortion": {"k1": -0.2}}), None)
    T_W_C = np.eye(4)
    T_W_C[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T_W_C[2, 3] = 400.0
    gt = honest.renderer.ground_truth(T_W_C)
    pinhole = honest.renderer.projector_distortion
    honest.renderer.projector_distortion = None
    honest.renderer._cache.clear()
    gt0 = honest.renderer.ground_truth(T_W_C)
    shift = np.linalg.norm(gt.projector_uv - gt0.projector_uv, axis=-1)
    assert pinhole is not None and np.nanmax(shift) > 0.05 and np.nanmin(shift) < np.nanmax(shift) / 10


def test_bad_world_section_names_the_file_and_field(tmp_path: Path) -> None:
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    data["world"]["hand_eye"]["translation_mm"] = -1.0
    bad = tmp_path / "cell.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"world\.hand_eye\.translation_mm") as info:
        load_cell_config(bad)
    assert str(bad) in str(info.value)
    data["world"] = {"hand_eyes": {}}
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="world.hand_eyes.*unknown key"):
        load_cell_config(bad)
    data["world"] = "idael"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="world"):
        load_cell_config(bad)


def test_world_schema_page_is_fresh() -> None:
    page = (REPO / "docs" / "world-schema.md").read_text()
    assert page == schema_page(), "docs/world-schema.md is stale: run `python -m fakes.sim.world`"
