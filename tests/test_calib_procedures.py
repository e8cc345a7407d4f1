"""The calibration routines as controller jobs over the device contracts (issue 12, Deliver 2).

The routines see the simulated world only through the camera, projector, robot and board stage; these tests
compare what they recover with the world's truth (fakes.sim.world.build_world), which tests may read.
The honest cells are sim.yaml's world (hand-eye 1.5 mm / 0.4 deg, lenses 0.5 %, projector pose, robot
kinematics); the binned camera (sim_binned_honest.yaml: sim_binned.yaml with that world) keeps each routine
to seconds, and its intrinsics and projector are calibrated once for the module's routines that need them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cell.calibration.handeye import pose_error
from cell.calibration.handeye_routines import HandEyeBoardJob, HandEyeIcpJob, KinematicsJob
from cell.calibration.operator_stage import OperatorBoardStage
from cell.calibration.procedures import CHARUCO, FLAT, Station
from cell.calibration.routines import run_routine
from cell.calibration.sensor_routines import IntrinsicsJob, ProjectorJob
from cell.calibration_state import calibration_state
from cell.config import DEFAULT_CELL, load_cell_config
from cell.contracts import BoardStage
from cell.devices import build_devices
from cell.errors import CalibrationError, DeviceFault
from cell.geometry import make_pose
from fakes.sim.world import build_world

BINNED = DEFAULT_CELL.parent / "sim_binned.yaml"


@pytest.fixture(scope="module")
def honest_binned() -> Path:
    """sim_binned.yaml (512x384 camera) in sim.yaml's honest world instead of the ideal one."""
    return DEFAULT_CELL.parent / "sim_binned_honest.yaml"


@pytest.fixture(scope="module")
def binned_intrinsics(honest_binned: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The intrinsics routine's result (8 board views) on the honest binned camera, run once for the tests of
    this module: one checks it, the others need the calibrated camera before their own routine."""
    folder = tmp_path_factory.mktemp("binned") / "intrinsics"
    return run_routine(IntrinsicsJob(load_cell_config(honest_binned), views=8), folder, honest_binned)


@pytest.fixture(scope="module")
def binned_projector(
    honest_binned: Path, binned_intrinsics: dict, tmp_path_factory: pytest.TempPathFactory
) -> dict:
    """The projector routine's result (8 views) with that calibrated camera, run once likewise."""
    cfg = load_cell_config(honest_binned)
    cfg.calibration.intrinsics = Path(binned_intrinsics["file"])
    return run_routine(
        ProjectorJob(cfg, views=8), tmp_path_factory.mktemp("binned") / "projector", honest_binned
    )


def test_robot_kinematics_halve_the_pose_dependent_error_on_the_part(
    tmp_path, honest_binned, binned_intrinsics
):
    """The kinematics routine (board views, the arm's link lengths and joint zeros with the hand-eye) on the
    honest world: the corners are explained to their noise where the nominal arm cannot, and the error of the
    point on the part over inspection views all around it (the world's truth, less the common offset the
    datums take) is at most half the nominal arm's with the mounting drawing."""
    from cell.calibration import active_kinematics
    from fakes.sim.pose_truth import part_error_spread

    cfg = load_cell_config(honest_binned)
    world = build_world(cfg)
    cfg.calibration.intrinsics = Path(binned_intrinsics["file"])  # the board poses need the calibrated camera
    r = run_routine(KinematicsJob(cfg), tmp_path / "kinematics", honest_binned)
    figures = r["summary"]
    assert figures["rms_px"] < 0.1 and figures["rms_px_nominal_arm"] > 2 * figures["rms_px"]
    cfg.calibration.kinematics = Path(r["file"])
    cfg.calibration.hand_eye = tmp_path / "kinematics" / "handeye.yaml"
    calibrated = part_error_spread(cfg, world, active_kinematics(cfg))
    nominal = part_error_spread(load_cell_config(honest_binned), world, None)
    assert calibrated < 0.5 * nominal, (calibrated, nominal)


def test_stages_are_board_stages_and_refuse_what_they_cannot_do():
    cfg = load_cell_config(DEFAULT_CELL)
    devices = build_devices(cfg, with_stage=True)
    stage = devices.stage
    assert isinstance(stage, BoardStage) and ("stage", stage) in devices.items()
    stage.connect()
    x, y, _ = Station().xyz_W
    with pytest.raises(DeviceFault, match=r"board-stage.*cannot reach height 900\.0 mm"):
        stage.place(FLAT, make_pose(np.eye(3), (x, y, 900.0)))
    answers = iter(["y", "no"])
    operator = OperatorBoardStage(ask=lambda prompt: next(answers))
    assert isinstance(operator, BoardStage)
    operator.place(CHARUCO, np.eye(4))
    with pytest.raises(DeviceFault, match="operator.*did not place"):
        operator.place(CHARUCO, np.eye(4))


def test_a_pose_where_the_board_is_not_found_is_one_clear_error(tmp_path):
    class EdgeOn(IntrinsicsJob):
        """One view with the board 250 mm to the side, out of the camera's 200 mm wide field."""

        def plan(self):
            views = super().plan()[:1]
            T = np.asarray(views[0].data["T_W_Bd"])
            T[0, 3] += 250.0
            views[0].data["T_W_Bd"] = T.tolist()
            return views

    cfg = load_cell_config(BINNED)  # the binned camera sees the same 200 mm wide field
    with pytest.raises(
        CalibrationError, match=r"view 0: the board 'charuco 11x8 15 mm' was not found.*world \("
    ):
        run_routine(EdgeOn(cfg, views=1), tmp_path / "edge", BINNED)


@pytest.mark.slow
def test_intrinsics_projector_and_board_hand_eye_recover_the_world(
    tmp_path, honest_binned, binned_intrinsics, binned_projector
):
    """On the binned camera in sim.yaml's world (measured: hand-eye 0.145 mm / 0.046 deg off the truth; the
    full camera's 0.10 mm / 0.031 deg; both within the bounds below, from 1.5 mm / 0.4 deg)."""
    cfg = load_cell_config(honest_binned)
    truth = build_world(cfg).sensor
    r = binned_intrinsics
    K = np.asarray(r["summary"]["K"])
    assert abs(cfg.sensor.camera.fx_px / truth.camera.fx_px - 1) > 0.004  # the config is 0.5 % off
    assert abs(K[0, 0] / truth.camera.fx_px - 1) < 0.001
    # The principal point is judged against the fit's own stated uncertainty: 8 board views give it to about
    # 0.5 px (1 sigma) on the binned camera, so a fixed 0.75 px bound failed on noise alone. Measured over
    # 5 seeds, errors (-0.53, -0.76), (0.23, 0.35), (0.63, 0.26), (-0.56, 0.23), (-0.18, 0.48) px against a
    # stated 0.44-0.58 (cx) and 0.32-0.41 (cy); seed 1 (this test's) 0.93 px. The stated sigma is bounded
    # (it grows with the corners' residuals: 0.78 px in cx when the refinement's window was too small).
    sd = np.asarray(r["summary"]["K_sd_px"])  # fx, fy, cx, cy
    err = np.array([K[0, 2] - truth.camera.cx_px, K[1, 2] - truth.camera.cy_px])
    assert np.all(sd[2:] < 0.65) and np.all(np.abs(err) < 3 * sd[2:]), (err, sd)
    cfg.calibration.intrinsics = Path(r["file"])

    r = binned_projector
    Kp = np.asarray(r["summary"]["K"])
    assert abs(Kp[0, 0] / truth.projector.fx_px - 1) < 0.003
    cfg.calibration.projector = Path(r["file"])

    r = run_routine(HandEyeBoardJob(cfg, views=12), tmp_path / "handeye", honest_binned)
    T_true = truth.T_T_C.matrix()
    assert pose_error(cfg.sensor.T_T_C.matrix(), T_true)[0] == pytest.approx(1.5, abs=1e-6)
    from cell.calibration.store import load_calibration

    _, arrays = load_calibration(Path(r["file"]), "hand_eye")
    _, lens = load_calibration(cfg.calibration.projector, "projector")  # its camera_K: the active lens
    dt, dr = pose_error(arrays["T_T_C"], T_true)
    # rotation by the lines of sight, as in the ICP test below (the frame's axes follow the principal point,
    # 1 px = 0.06 deg on the binned camera: measured 0.067 deg with the principal point 0.93 px off)
    worst = sight_error_deg(arrays["T_T_C"], lens["camera_K"], T_true, truth.camera)
    assert dt < 0.25 and worst < 0.05, (dt, dr, worst)  # from 1.5 mm / 0.4 deg (robot kinematics remain)
    journal = (tmp_path / "handeye" / "journal.jsonl").read_text()
    assert '"state": "done"' in journal and '"device": "board-stage"' in journal
    # each file records the cell config it was made for, so a run with this config finds all three current
    # (they once recorded none, and every run that required calibration was judged incomplete)
    cfg.calibration.hand_eye = Path(r["file"])
    state = calibration_state(cfg, required=True)
    assert [f["made_for_this_config"] for f in state["files"]] == [True, True, True], state
    assert state["incomplete_reasons"] == [], state


@pytest.mark.slow
def test_icp_of_gauge_scans_from_the_mounting_drawing_recovers_the_hand_eye(
    tmp_path, honest_binned, binned_intrinsics, binned_projector
):
    cfg = load_cell_config(honest_binned)
    truth = build_world(cfg).sensor
    cfg.calibration.intrinsics = Path(binned_intrinsics["file"])
    cfg.calibration.projector = Path(binned_projector["file"])
    r = run_routine(HandEyeIcpJob(cfg, every=5), tmp_path / "icp", honest_binned)
    assert r["summary"]["converged"]
    from cell.calibration.store import load_calibration

    _, arrays = load_calibration(Path(r["file"]), "hand_eye")
    _, lens = load_calibration(cfg.calibration.projector, "projector")  # its camera_K: the active lens
    T, T_true = arrays["T_T_C"], truth.T_T_C.matrix()
    dt, _ = pose_error(T, T_true)
    # The camera frame's axes are defined by its principal point, which 8 board views give to about 1 px
    # (0.06 deg on the binned camera): a hand-eye turned by that much is right for the camera it belongs to.
    # So its rotation is judged by where the camera looks in the flange frame (the lines of sight through the
    # image's centre and corners), as a measurement sees it; measured 0.006 deg (the frames' axes: 0.10 deg).
    worst = sight_error_deg(T, lens["camera_K"], T_true, truth.camera)
    assert dt < 0.6 and worst < 0.06, (dt, worst)  # from 1.5 mm / 0.4 deg; measured 0.33 mm, 0.006 deg


def sight_error_deg(T_T_C: np.ndarray, K: np.ndarray, T_true: np.ndarray, cam) -> float:
    """The largest angle (deg) between the calibrated and the true lines of sight in the flange frame through
    the image's centre and two corners: the hand-eye's rotation as a measurement sees it."""
    worst = 0.0
    for u, v in ((cam.width_px / 2, cam.height_px / 2), (0, 0), (cam.width_px, cam.height_px)):
        ray, ray_true = np.linalg.solve(K, (u, v, 1.0)), np.linalg.solve(cam.K(), (u, v, 1.0))
        a = T_T_C[:3, :3] @ ray / np.linalg.norm(ray)
        b = T_true[:3, :3] @ ray_true / np.linalg.norm(ray_true)
        worst = max(worst, float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0)))))
    return worst


def test_demo_reuses_a_calibration_only_of_the_same_cell_file(tmp_path):
    from cell.calibration.routines import _digest, valid_calibration

    cell = tmp_path / "cell.yaml"
    cell.write_text(DEFAULT_CELL.read_text())
    folder = tmp_path / "calibration"
    folder.mkdir()
    assert valid_calibration(cell, folder) is None  # nothing there
    (folder / "cell.yaml").write_text(DEFAULT_CELL.read_text())
    (folder / "calibration.json").write_text(json.dumps({"source_sha256": _digest(cell)}))
    assert valid_calibration(cell, folder) == folder / "cell.yaml"
    cell.write_text(DEFAULT_CELL.read_text() + "\n# edited\n")  # the cell changed: calibrate again
    assert valid_calibration(cell, folder) is None
