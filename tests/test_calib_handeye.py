"""Hand-eye calibration against the simulator's truth: AX=XB solvers from board poses (solvePnP on projected
board corners with pixel noise) and the dissertation's ICP method on gauge scans (ground-truth points +
noise)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.analysis.errormap import NominalMesh
from cell.calibration.boards import board_pose_from_corners
from cell.calibration.capture_folder import ChessboardTarget
from cell.calibration.handeye import GaugeView, handeye_from_board_poses, handeye_icp, pose_error
from cell.config import DEFAULT_CELL, PoseConfig, load_cell_config
from cell.errors import CalibrationError
from cell.geometry import invert, look_at, make_pose, transform_points
from cell.mesh import load_mesh
from cell.planning.kinematics import UR5E
from fakes.sim.optics import project_points
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene

GAUGE = DEFAULT_CELL.parent.parent / "parts" / "gauge.stl"


@pytest.fixture(scope="module")
def cfg():
    c = load_cell_config(DEFAULT_CELL)
    # a hand-eye with every component non-zero, so that no solver can pass by returning a trivial rotation
    c.sensor.T_T_C = PoseConfig(xyz_mm=(1.7, -60.4, 80.9), rpy_deg=(0.6, -1.1, 2.3))
    return c


def _reachable_views(cfg, target_W, n, rng, tilt_deg=30.0, dist_mm=420.0):
    """Flange poses T_B_T from FK of joint sets that look at ``target_W`` from random directions."""
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), cfg.sensor.T_T_C.matrix()
    out = []
    while len(out) < n:
        tilt, az, roll = (
            np.radians(rng.uniform(5, tilt_deg)),
            rng.uniform(0, 2 * np.pi),
            rng.uniform(-0.6, 0.6),
        )
        eye = target_W + dist_mm * np.array(
            [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)]
        )
        T_W_C = look_at(eye, target_W) @ make_pose(Rotation.from_rotvec([0, 0, roll]).as_matrix())
        T_B_T = invert(T_W_B) @ T_W_C @ invert(T_T_C)
        sols = UR5E.ik(T_B_T, allow_singular=False)
        if sols.ok:
            out.append(UR5E.fk(sols.joints[0]))
    return out


def test_board_pose_solvers_recover_hand_eye(cfg):
    rng = np.random.default_rng(3)
    cam = cfg.sensor.camera
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), cfg.sensor.T_T_C.matrix()
    target = np.array([-100.0, 50.0, 0.0])
    T_W_Bd = make_pose(Rotation.from_euler("z", 20, degrees=True).as_matrix(), target - (80, 60, 0))
    obj = ChessboardTarget((9, 7), 20.0).getChessboardCorners().astype(np.float64)
    flange, board = [], []
    for T_B_T in _reachable_views(cfg, target, 25, rng, tilt_deg=45):
        T_C_Bd = invert(T_W_B @ T_B_T @ T_T_C) @ T_W_Bd
        uv = project_points(cam, transform_points(T_C_Bd, obj)) + rng.normal(0, 0.05, (len(obj), 2))
        flange.append(T_B_T)
        board.append(board_pose_from_corners(obj, uv, cam.K(), cam.distortion.as_array()))
    for method in ("tsai", "park", "daniilidis"):
        dt, dr = pose_error(handeye_from_board_poses(flange, board, method), T_T_C)
        assert dt < 0.05 and dr < 0.01, (method, dt, dr)


def test_board_pose_solvers_reject_bad_input(cfg):
    T = np.eye(4)
    with pytest.raises(CalibrationError, match="at least 3"):
        handeye_from_board_poses([T, T], [T, T])
    spins = [make_pose(Rotation.from_rotvec([0, 0, a]).as_matrix(), (a, 0, 0)) for a in (0.1, 0.5, 0.9, 1.3)]
    with pytest.raises(CalibrationError, match="single axis"):
        handeye_from_board_poses(spins, spins)


@pytest.mark.slow
def test_icp_hand_eye_on_gauge_scans(cfg):
    rng = np.random.default_rng(5)
    gauge = load_mesh(GAUGE)
    T_W_P = make_pose(Rotation.from_euler("z", 12, degrees=True).as_matrix(), (-120.0, 60.0, 0.0))
    part_W = gauge.copy().apply_transform(T_W_P)
    renderer = SceneRenderer(cfg.sensor, cfg.sim, Scene.from_meshes(part_W, cfg.sim))
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), cfg.sensor.T_T_C.matrix()
    centre = T_W_P[:3, 3] + (0, 0, 15)
    views = []
    # oblique views at three corners: the top and two side faces in each, so every view pins all six dof
    for az in np.radians([57, 147, 237]):
        eye = centre + 400 * np.array([np.sin(0.87) * np.cos(az), np.sin(0.87) * np.sin(az), np.cos(0.87)])
        T_B_T = UR5E.fk(
            UR5E.ik(invert(T_W_B) @ look_at(eye, centre) @ invert(T_T_C), allow_singular=False).joints[0]
        )
        gt = renderer.ground_truth(T_W_B @ T_B_T @ T_T_C)
        p = gt.points_C[gt.part][::40]  # simulated scan: true points + the sensor's 0.016 mm noise
        views.append(GaugeView(p + rng.normal(0, 0.016, p.shape), T_B_T))
    # start from the nominal mounting drawing: ~1.5 mm and 0.5 deg off
    T_init = T_T_C @ make_pose(
        Rotation.from_euler("xyz", [0.4, -0.3, 0.25], degrees=True).as_matrix(), (1.0, -0.8, 0.6)
    )
    res = handeye_icp(NominalMesh.from_trimesh(gauge), views, T_W_B, T_W_P, T_init)
    dt, dr = pose_error(res.T_T_C, T_T_C)
    assert pose_error(T_init, T_T_C)[0] > 1.0
    assert res.converged
    assert dt < 0.05 and dr < 0.01, (dt, dr, len(res.cost_mm2))
    assert res.rms_mm == pytest.approx(0.016, rel=0.25)  # what is left is the sensor noise
