"""The routines that place the sensor on the robot as controller jobs: hand-eye from board poses, the arm's
kinematics from the same poses, and hand-eye by ICP of gauge scans."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.calibration.active import (
    active_hand_eye,
    active_measuring_patterns,
    active_sensor_config,
    active_triangulator,
)
from cell.calibration.boards import board_pose_from_corners
from cell.calibration.handeye import GaugeView, handeye_from_board_poses, handeye_icp, pose_error
from cell.calibration.kinematics import BoardObservation, fit_kinematics
from cell.calibration.procedures import (
    CHARUCO,
    GAUGE,
    CalibrationJob,
    _view,
    camera_over,
    charuco,
    detect_board,
    flange_for_camera,
    load_view_arrays,
    save_view_arrays,
)
from cell.calibration.store import save_calibration
from cell.config import CellConfig
from cell.errors import CalibrationError
from cell.geometry import Pose, make_pose, transform_points
from cell.run_data import View
from cell.runs import RunFolder
from cell.sensing.decode import decode
from cell.sensing.patterns import PatternSet


def _handeye_meta(T_T_C: Pose, figs: dict[str, Any], quality: dict[str, float]) -> dict[str, Any]:
    return {"T_T_C": T_T_C.tolist(), "figures": figs, "quality": quality}


class HandEyeBoardJob(CalibrationJob):
    """``T_T_C`` from board poses (Tsai, Park or Daniilidis): the ChArUco board lies still on the stage, the
    robot looks at it from ``views`` poses (tilted 15-30 deg around it, rolled), the board pose in the camera
    comes from solvePnP with the active camera intrinsics."""

    kind, file_stem = "hand_eye", "handeye"

    def __init__(self, cfg: CellConfig, views: int = 12, method: str = "park", **kw: Any) -> None:
        super().__init__(cfg, **kw)
        self.n_views, self.method = views, method

    def still_board(self) -> tuple[NDArray[np.float64], Pose]:
        """The board lying still on the station: its top centre ({W}, mm) and ``T_W_Bd``, centred under the
        camera looking straight down from the stand-off."""
        top = self.station.point(self.station.board_top_mm)
        nx, ny = CHARUCO.squares
        T_C_Bd = make_pose(
            np.eye(3), (-nx * CHARUCO.square_mm / 2, -ny * CHARUCO.square_mm / 2, self.cfg.sensor.standoff_mm)
        )
        return top, camera_over(self.cfg, top) @ T_C_Bd

    def plan(self) -> list[View]:
        top, T_W_Bd = self.still_board()
        out = []
        for k in range(self.n_views):
            tilt = 15.0 + 15.0 * (k % 2)
            T_W_C = camera_over(self.cfg, top, tilt, 360.0 * k / self.n_views, 20.0 * ((k % 3) - 1))
            out.append(_view(flange_for_camera(self.cfg, T_W_C), CHARUCO, T_W_Bd, index=k))
        return out

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        found = detect_board(view, captured["images"][0])
        cam = active_sensor_config(self.cfg).camera
        T_C_Bd = board_pose_from_corners(
            found.object_points(charuco(CHARUCO)), found.corners_px, cam.K(), cam.distortion.as_array()
        )
        save_view_arrays(out_dir, T_C_Bd=T_C_Bd, corners_px=found.corners_px, ids=found.ids)
        return {"corners": int(len(found.ids))}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        done = self.view_summaries(run)
        T_B_T = [np.asarray(s["T_B_T"]) for _, s in done]
        T_C_Bd = [load_view_arrays(run, i)["T_C_Bd"] for i, _ in done]
        if len(done) < 3:
            raise CalibrationError(f"hand-eye from board poses: {len(done)} views, at least 3 are needed")
        X = handeye_from_board_poses(T_B_T, T_C_Bd, self.method)  # type: ignore[arg-type]
        T_W_B = self.cfg.robot.T_W_B.matrix()
        board_W = np.array([(T_W_B @ a @ X @ b)[:3, 3] for a, b in zip(T_B_T, T_C_Bd)])
        spread = float(np.sqrt(np.mean(np.sum((board_W - board_W.mean(0)) ** 2, axis=1))))
        dt, dr = pose_error(X, self.cfg.sensor.T_T_C.matrix())
        figs = {
            "method": self.method,
            "views": len(done),
            "points": len(done),
            "board_position_spread_mm": spread,
            "change_from_config_mm": dt,
            "change_from_config_deg": dr,
        }
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {"T_T_C": X},
            _handeye_meta(X, figs, {"rms_mm": spread}),
            "quality.rms_mm",
            self.force,
            made_for=self.made_for,
        )
        return figs, path


class KinematicsJob(HandEyeBoardJob):
    """The robot's link-length and joint-zero errors with the hand-eye (cell.calibration.kinematics): the
    ChArUco board lies still on the stage and the robot looks at it from ``views`` poses spread in tilt
    (10-35 deg), azimuth, roll and distance (stand-off -+40 mm), so that the joints move through as much of
    their range as the board allows. Writes ``kinematics`` (robot_kinematics) and ``handeye`` (hand_eye, the
    T_T_C found with them: the two belong together)."""

    kind, file_stem = "robot_kinematics", "kinematics"

    def __init__(self, cfg: CellConfig, views: int = 24, **kw: Any) -> None:
        super().__init__(cfg, views=views, **kw)

    def plan(self) -> list[View]:
        top, T_W_Bd = self.still_board()
        out = []
        for k in range(self.n_views):
            tilt = 10.0 + 12.5 * (k % 3)
            T_W_C = camera_over(self.cfg, top, tilt, 360.0 * k / self.n_views, 25.0 * ((k % 5) - 2))
            T_W_C[:3, 3] += T_W_C[:3, 2] * (40.0 if k % 2 else -40.0)  # nearer, farther than the stand-off
            out.append(_view(flange_for_camera(self.cfg, T_W_C), CHARUCO, T_W_Bd, index=k))
        return out

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        found = detect_board(view, captured["images"][0])
        cam = active_sensor_config(self.cfg).camera
        obj = found.object_points(charuco(CHARUCO))
        T_C_Bd = board_pose_from_corners(obj, found.corners_px, cam.K(), cam.distortion.as_array())
        save_view_arrays(out_dir, T_C_Bd=T_C_Bd, corners_px=found.corners_px, ids=found.ids, object_mm=obj)
        return {"corners": int(len(found.ids))}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        done = self.view_summaries(run)
        observed = []
        for i, summary in done:
            v = load_view_arrays(run, i)
            observed.append(
                BoardObservation(
                    np.asarray(summary["joints"]), v["corners_px"].reshape(-1, 2), v["object_mm"]
                )
            )
        cam = active_sensor_config(self.cfg).camera
        first = load_view_arrays(run, done[0][0])["T_C_Bd"] if done else np.eye(4)
        fit = fit_kinematics(observed, cam.K(), cam.distortion.as_array(), active_hand_eye(self.cfg), first)
        dt, dr = pose_error(fit.T_T_C, self.cfg.sensor.T_T_C.matrix())
        figs = {
            "views": len(done),
            "points": int(sum(len(o.corners_px) for o in observed)),
            "rms_px": fit.rms_px,
            "rms_px_nominal_arm": fit.rms_px_nominal_arm,
            "worst_view_px": max(fit.per_view_px),
            "link_errors_mm": {
                "d": np.round(fit.errors.dd, 4).tolist(),
                "a": np.round(fit.errors.da, 4).tolist(),
            },
            "joint_zero_errors_deg": np.round(np.rad2deg(fit.errors.dq), 5).tolist(),
            "hand_eye_change_from_config_mm": dt,
            "hand_eye_change_from_config_deg": dr,
        }
        save_calibration(
            run.path / "handeye",
            "hand_eye",
            {"T_T_C": fit.T_T_C},
            _handeye_meta(fit.T_T_C, {**figs, "method": "with the robot kinematics"}, {"rms_px": fit.rms_px}),
            force=True,  # it belongs to the kinematics below, which the quality check guards
            made_for=self.made_for,
        )
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {
                "dd": fit.errors.dd,
                "da": fit.errors.da,
                "dq": fit.errors.dq,
                "T_T_C": fit.T_T_C,
                "T_B_Bd": fit.T_B_Bd,
                "x": fit.x,  # with its covariance: how far apart views may still be (view_pose_prior)
                "covariance": fit.covariance,
            },
            {
                "robot": {"name": self.cfg.robot.name, "model": self.cfg.robot.model},
                "figures": figs,
                "quality": {"rms_px": fit.rms_px},
            },
            "quality.rms_px",
            self.force,
            made_for=self.made_for,
        )
        return figs, path


class HandEyeIcpJob(CalibrationJob):
    """``T_T_C`` by ICP of gauge scans against the gauge CAD (dissertation 4.1.3): the stage sets the gauge at
    the station, the robot scans it from four corners through the GCLS pipeline with the cell's active
    sensor calibration, and the ICP starts from the mounting drawing (the config's ``sensor.T_T_C``)."""

    kind, file_stem = "hand_eye", "handeye"

    def __init__(self, cfg: CellConfig, every: int = 20, tilt_deg: float = 35.0, **kw: Any) -> None:
        super().__init__(cfg, **kw)
        self.tilt_deg = tilt_deg  # views from the four corners, this far from vertical: the sides pin x and y
        self.every = every
        self.table_margin_mm = 5.0  # keep every n-th valid point of a scan (ICP cost; ~10^4 points per view)

    @property
    def T_W_P(self) -> Pose:
        return make_pose(np.eye(3), self.station.point(0.0))

    def plan(self) -> list[View]:
        centre = self.station.point(15.0)
        out = []
        for k, az in enumerate((45.0, 135.0, 225.0, 315.0)):
            T_W_C = camera_over(self.cfg, centre, self.tilt_deg, az)
            out.append(_view(flange_for_camera(self.cfg, T_W_C), GAUGE, self.T_W_P, index=k))
        return out

    def patterns(self, view: View) -> PatternSet:
        return active_measuring_patterns(self.cfg)  # through the gamma LUT, if any

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        dec = decode(captured["images"], self.patterns(view), self.cfg.sensor.camera.bit_depth)
        cloud = active_triangulator(self.cfg).triangulate(dec)
        pts = cloud.points_C[cloud.valid][:: self.every]
        save_view_arrays(out_dir, points_C=pts)
        return {"points": int(len(pts))}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        from cell.analysis.errormap import NominalMesh
        from cell.mesh import load_mesh

        start = self.cfg.sensor.T_T_C.matrix()
        T_W_B = self.cfg.robot.T_W_B.matrix()
        scans = []
        for i, s in self.view_summaries(run):
            p_C, T_B_T = load_view_arrays(run, i)["points_C"], np.asarray(s["T_B_T"])
            # the table the gauge stands on is no part of its CAD: leave out what the mounting drawing puts
            # within table_margin_mm of the table plane (a 0.4 deg hand-eye error moves points ~3 mm at
            # 400 mm)
            z_W = transform_points(T_W_B @ T_B_T @ start, p_C)[:, 2]
            scans.append(GaugeView(p_C[z_W > self.station.xyz_W[2] + self.table_margin_mm], T_B_T))
        gauge = NominalMesh.from_trimesh(load_mesh(GAUGE_PATH))
        res = handeye_icp(gauge, scans, T_W_B, self.T_W_P, start)
        dt, dr = pose_error(res.T_T_C, start)
        figs = {
            "method": "icp",
            "views": len(scans),
            "points": int(sum(len(s.points_C) for s in scans)),
            "iterations": len(res.cost_mm2),
            "converged": res.converged,
            "rms_mm": res.rms_mm,
            "change_from_config_mm": dt,
            "change_from_config_deg": dr,
        }
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {"T_T_C": res.T_T_C},
            _handeye_meta(res.T_T_C, figs, {"rms_mm": res.rms_mm}),
            "quality.rms_mm",
            self.force,
            made_for=self.made_for,
        )
        return figs, path


GAUGE_PATH = Path(GAUGE.mesh_path or "")
