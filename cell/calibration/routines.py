"""The routines (intrinsics, projector, gamma, sensor, hand-eye from board poses, hand-eye by ICP of gauge
scans, validation) as :class:`cell.calibration.procedures.CalibrationJob` subclasses, the runner that puts
one under the controller, and ``calibrate_all`` that chains them into one calibration folder."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
import yaml
from numpy.typing import NDArray

from cell.calibration.active import active_hand_eye, active_sensor_config, active_triangulator
from cell.calibration.boards import board_pose_from_corners
from cell.calibration.gamma import gamma_figures, grey_levels, linearising_lut, measure_response
from cell.calibration.handeye import GaugeView, handeye_from_board_poses, handeye_icp
from cell.calibration.intrinsics import CharucoView, calibrate_intrinsics, detect_charuco
from cell.calibration.kinematics import BoardObservation, fit_kinematics
from cell.calibration.procedures import (
    CHARUCO,
    FLAT,
    GAUGE,
    GAUGE_CERTIFICATE,
    CalibrationJob,
    JointMotion,
    _pose_text,
    _view,
    camera_over,
    charuco,
    charuco_poses,
    flange_for_camera,
)
from cell.calibration.projector import calibrate_projector, corners_in_projector
from cell.calibration.store import load_calibration, save_calibration
from cell.calibration.validation import fit_plane, flat_test, load_gauge_certificate, slot_test, sphere_test
from cell.config import CellConfig, load_cell_config
from cell.controller import Controller, ControllerSettings, RobotLimits
from cell.devices import build_devices
from cell.errors import CalibrationError, ConfigError, RoutinePaused
from cell.geometry import Pose, invert, make_pose, transform_points
from cell.planning.kinematics import UR5E
from cell.run_data import View
from cell.runs import RunFolder, write_json_atomic
from cell.sensing.decode import decode
from cell.sensing.patterns import (
    PatternSet,
    measuring_patterns,
    projector_calibration_patterns,
    sensor_calibration_patterns,
    uniform_patterns,
)
from cell.sensing.triangulate import ReferencePlaneTriangulator


def _board_not_found(view: View, index: int | str) -> CalibrationError:
    return CalibrationError(
        f"view {index}: the board '{view.data['board']}' was not found in the camera image (requested at "
        f"{_pose_text(view.data['T_W_Bd'])}, robot flange at {_pose_text(view.T_B_T)}); check that the board "
        "is in view, lit and in focus"
    )


def _detect(view: View, image: Any) -> CharucoView:
    found = detect_charuco(image, charuco(CHARUCO))
    if found is None:
        raise _board_not_found(view, view.data.get("index", "?"))
    return found


def _save_view(out_dir: Path, **arrays: Any) -> None:
    with open(out_dir / "data.npz", "wb") as f:
        np.savez(f, **arrays)


def _load_view(run: RunFolder, i: int) -> dict[str, Any]:
    with np.load(run.view_dir(i) / "data.npz") as d:
        return {k: d[k] for k in d.files}


# --------------------------------------------------------------------------------------------- intrinsics
class IntrinsicsJob(CalibrationJob):
    """Camera K and distortion: the stage holds the ChArUco board at ``views`` poses in front of the camera
    (OpenCV CharucoDetector, calibrateCamera, k3 fixed)."""

    kind, file_stem = "camera_intrinsics", "intrinsics"

    def __init__(self, cfg: CellConfig, views: int = 12, **kw: Any) -> None:
        super().__init__(cfg, **kw)
        self.n_views = views

    def plan(self) -> list[View]:
        T_W_C = camera_over(self.cfg, self.station.point(self.station.board_top_mm))
        T_B_T = flange_for_camera(self.cfg, T_W_C)
        rng = np.random.default_rng(self.seed)
        poses = charuco_poses(CHARUCO, self.cfg.sensor.standoff_mm, self.n_views, rng)
        return [_view(T_B_T, CHARUCO, T_W_C @ T, index=i) for i, T in enumerate(poses)]

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        found = _detect(view, captured["images"][0])
        _save_view(out_dir, corners_px=found.corners_px, ids=found.ids)
        return {"corners": int(len(found.ids))}

    def _charuco_views(self, run: RunFolder) -> list[CharucoView]:
        return [
            CharucoView(d["corners_px"], d["ids"])
            for d in map(lambda i: _load_view(run, i), run.completed_views())
        ]

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        cam = self.cfg.sensor.camera
        res = calibrate_intrinsics(self._charuco_views(run), charuco(CHARUCO), (cam.width_px, cam.height_px))
        figs = {
            "views": len(res.view_rms_px),
            "corners": int(sum(len(v.ids) for v in self._charuco_views(run))),
            "rms_px": res.rms_px,
            "max_view_rms_px": float(res.view_rms_px.max()),
            "K": res.K.tolist(),
            "dist": res.dist.tolist(),
        }
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {"K": res.K, "dist": res.dist},
            {
                "camera": {"serial": cam.serial, "resolution": [cam.width_px, cam.height_px]},
                "figures": figs,
                "quality": {"rms_px": res.rms_px},
            },
            "quality.rms_px",
            self.force,
        )
        return figs, path


# --------------------------------------------------------------------------------------------- projector
class ProjectorJob(IntrinsicsJob):
    """Projector K and T_C_P (Moreno-Taubin): GCPS in both directions on the ChArUco board, a local homography
    per corner, calibrateCamera for the projector and stereoCalibrate with the camera fixed. The camera is the
    cell's active one (calibration.intrinsics) unless ``intrinsics`` names a file."""

    kind, file_stem = "projector", "projector"

    def __init__(self, cfg: CellConfig, views: int = 6, intrinsics: Path | None = None, **kw: Any) -> None:
        super().__init__(cfg, views=views, **kw)
        self.intrinsics = intrinsics

    def patterns(self, view: View) -> PatternSet:
        return projector_calibration_patterns(self.cfg.sensor.projector)

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        images = captured["images"]
        found = _detect(view, images[0])
        ps = self.patterns(view)
        dec = decode(images, ps, self.cfg.sensor.camera.bit_depth)
        pp, ok = corners_in_projector(found, dec.axes["columns"].u, dec.axes["rows"].u)
        _save_view(out_dir, corners_px=found.corners_px, ids=found.ids, proj_px=pp, ok=ok)
        return {"corners": int(len(found.ids)), "decoded_corners": int(ok.sum())}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        cam, proj = self.cfg.sensor.camera, self.cfg.sensor.projector
        active = active_sensor_config(self.cfg).camera
        K, dist = active.K(), active.distortion.as_array()
        if self.intrinsics is not None:
            _, arrays = load_calibration(self.intrinsics, "camera_intrinsics")
            K, dist = arrays["K"], arrays["dist"]
        data = [_load_view(run, i) for i in run.completed_views()]
        res = calibrate_projector(
            [CharucoView(d["corners_px"], d["ids"]) for d in data],
            [d["proj_px"] for d in data],
            [d["ok"] for d in data],
            charuco(CHARUCO),
            K,
            dist,
            (cam.width_px, cam.height_px),
            (proj.width_px, proj.height_px),
        )
        figs = {
            "views": res.views,
            "corners": res.corners,
            "rms_px": res.rms_px,
            "stereo_rms_px": res.stereo_rms_px,
            "K": res.K.tolist(),
            "dist": res.dist.tolist(),
            "T_C_P": res.T_C_P.tolist(),
        }
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {"K": res.K, "dist": res.dist, "T_C_P": res.T_C_P},
            {
                "projector": {"serial": proj.serial, "resolution": [proj.width_px, proj.height_px]},
                "figures": figs,
                "quality": {"rms_px": res.stereo_rms_px},
            },
            "quality.rms_px",
            self.force,
        )
        return figs, path


# --------------------------------------------------------------------------------------------- flat board
class _FlatBoardJob(CalibrationJob):
    """Routines on the flat white board under a camera looking straight down at it."""

    def board_view(self, height_mm: float, **extra: Any) -> View:
        top = self.station.point(self.station.board_top_mm)
        T_B_T = flange_for_camera(self.cfg, camera_over(self.cfg, top))
        return _view(
            T_B_T, FLAT, make_pose(np.eye(3), top + (0.0, 0.0, height_mm)), height_mm=height_mm, **extra
        )


class GammaJob(_FlatBoardJob):
    """Projector response: uniform grey levels on the white board -> linearising LUT."""

    kind, file_stem = "projector_gamma", "gamma"

    def __init__(self, cfg: CellConfig, levels: int = 17, **kw: Any) -> None:
        super().__init__(cfg, **kw)
        self.levels = grey_levels(levels)

    def plan(self) -> list[View]:
        return [self.board_view(0.0, index=0)]

    def patterns(self, view: View) -> PatternSet:
        return uniform_patterns(self.cfg.sensor.projector, [int(g) for g in self.levels])

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        response = measure_response(captured["images"], self.levels)
        _save_view(out_dir, response=response)
        return {"levels": len(self.levels)}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        response = _load_view(run, run.completed_views()[0])["response"]
        figs = {**gamma_figures(self.levels, response), "points": len(self.levels)}
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {"lut": linearising_lut(self.levels, response)},
            {"projector": {"name": self.cfg.sensor.projector.name}, "figures": figs},
            force=self.force,
        )
        return figs, path


class SensorJob(_FlatBoardJob):
    """Per-pixel d, S, alpha (dissertation 2.2, 5.1.1): the stage steps the white board ``steps`` x
    ``step_mm``
    toward the sensor; GCLS in both directions at every step."""

    kind, file_stem = "sensor_per_pixel", "sensor"

    def __init__(
        self, cfg: CellConfig, steps: int = 30, step_mm: float = 1.0, points: int = 65536, **kw: Any
    ):
        super().__init__(cfg, **kw)
        self.steps, self.step_mm, self.points = steps, step_mm, points

    def plan(self) -> list[View]:
        return [self.board_view(k * self.step_mm, index=k) for k in range(self.steps + 1)]

    def patterns(self, view: View) -> PatternSet:
        return sensor_calibration_patterns(self.cfg.sensor.projector)

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        dec = decode(captured["images"], self.patterns(view), self.cfg.sensor.camera.bit_depth)
        u, v = dec.axes["columns"].u, dec.axes["rows"].u
        _save_view(out_dir, u=u.astype(np.float32), v=v.astype(np.float32))
        return {"decoded": int((np.isfinite(u) & np.isfinite(v)).sum())}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        from types import SimpleNamespace

        from cell.calibration.sensor import SensorCalibrator, save_sensor_calibration

        cfg = self.cfg
        cam = active_sensor_config(cfg).camera  # the calibrated lens when calibration.intrinsics is set
        cal = SensorCalibrator(
            cam,
            cfg.sensor.projector,
            cfg.sensor.standoff_mm,
            n_points=self.points,
            eval_height_mm=cfg.sensor.depth_of_field_mm / 2,
        )
        for i in run.completed_views():
            d = _load_view(run, i)
            axes = {
                "columns": SimpleNamespace(u=d["u"].astype(np.float64)),
                "rows": SimpleNamespace(u=d["v"].astype(np.float64)),
            }
            decoded = SimpleNamespace(axes=axes)  # the u, v maps are all add_step reads
            found = cal.add_step(float(views[i].data["height_mm"]), decoded)  # type: ignore[arg-type]
            run.log("step", index=i, height_mm=views[i].data["height_mm"], encoded_points=found)
        res = cal.finish()
        path = save_sensor_calibration(
            res,
            run.path / self.file_stem,
            cam,
            cfg.sensor.projector,
            force=self.force,
            reference_T_B_T=np.asarray(dict(self.view_summaries(run))[0]["T_B_T"]),
        )
        return {**res.figures, "points": int(len(res.points_px))}, path


# --------------------------------------------------------------------------------------------- hand-eye
def _handeye_meta(T_T_C: Pose, figs: dict[str, Any], quality: dict[str, float]) -> dict[str, Any]:
    return {"T_T_C": T_T_C.tolist(), "figures": figs, "quality": quality}


def _change(T: Pose, T0: Pose) -> tuple[float, float]:
    from cell.calibration.handeye import pose_error

    return pose_error(T, T0)


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
        found = _detect(view, captured["images"][0])
        cam = active_sensor_config(self.cfg).camera
        T_C_Bd = board_pose_from_corners(
            found.object_points(charuco(CHARUCO)), found.corners_px, cam.K(), cam.distortion.as_array()
        )
        _save_view(out_dir, T_C_Bd=T_C_Bd, corners_px=found.corners_px, ids=found.ids)
        return {"corners": int(len(found.ids))}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        done = self.view_summaries(run)
        T_B_T = [np.asarray(s["T_B_T"]) for _, s in done]
        T_C_Bd = [_load_view(run, i)["T_C_Bd"] for i, _ in done]
        if len(done) < 3:
            raise CalibrationError(f"hand-eye from board poses: {len(done)} views, at least 3 are needed")
        X = handeye_from_board_poses(T_B_T, T_C_Bd, self.method)  # type: ignore[arg-type]
        T_W_B = self.cfg.robot.T_W_B.matrix()
        board_W = np.array([(T_W_B @ a @ X @ b)[:3, 3] for a, b in zip(T_B_T, T_C_Bd)])
        spread = float(np.sqrt(np.mean(np.sum((board_W - board_W.mean(0)) ** 2, axis=1))))
        dt, dr = _change(X, self.cfg.sensor.T_T_C.matrix())
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
        found = _detect(view, captured["images"][0])
        cam = active_sensor_config(self.cfg).camera
        obj = found.object_points(charuco(CHARUCO))
        T_C_Bd = board_pose_from_corners(obj, found.corners_px, cam.K(), cam.distortion.as_array())
        _save_view(out_dir, T_C_Bd=T_C_Bd, corners_px=found.corners_px, ids=found.ids, object_mm=obj)
        return {"corners": int(len(found.ids))}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        done = self.view_summaries(run)
        observed = []
        for i, summary in done:
            v = _load_view(run, i)
            observed.append(
                BoardObservation(
                    np.asarray(summary["joints"]), v["corners_px"].reshape(-1, 2), v["object_mm"]
                )
            )
        cam = active_sensor_config(self.cfg).camera
        first = _load_view(run, done[0][0])["T_C_Bd"] if done else np.eye(4)
        fit = fit_kinematics(observed, cam.K(), cam.distortion.as_array(), active_hand_eye(self.cfg), first)
        dt, dr = _change(fit.T_T_C, self.cfg.sensor.T_T_C.matrix())
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
        return measuring_patterns(self.cfg.sensor.projector)

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        dec = decode(captured["images"], self.patterns(view), self.cfg.sensor.camera.bit_depth)
        cloud = active_triangulator(self.cfg).triangulate(dec)
        pts = cloud.points_C[cloud.valid][:: self.every]
        _save_view(out_dir, points_C=pts)
        return {"points": int(len(pts))}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        from cell.analysis.errormap import NominalMesh
        from cell.mesh import load_mesh

        start = self.cfg.sensor.T_T_C.matrix()
        T_W_B = self.cfg.robot.T_W_B.matrix()
        scans = []
        for i, s in self.view_summaries(run):
            p_C, T_B_T = _load_view(run, i)["points_C"], np.asarray(s["T_B_T"])
            # the table the gauge stands on is no part of its CAD: leave out what the mounting drawing puts
            # within table_margin_mm of the table plane (a 0.4 deg hand-eye error moves points ~3 mm at
            # 400 mm)
            z_W = transform_points(T_W_B @ T_B_T @ start, p_C)[:, 2]
            scans.append(GaugeView(p_C[z_W > self.station.xyz_W[2] + self.table_margin_mm], T_B_T))
        gauge = NominalMesh.from_trimesh(load_mesh(GAUGE_PATH))
        res = handeye_icp(gauge, scans, T_W_B, self.T_W_P, start)
        dt, dr = _change(res.T_T_C, start)
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
        )
        return figs, path


GAUGE_PATH = Path(GAUGE.mesh_path or "")


# --------------------------------------------------------------------------------------------- validation
class ValidateJob(_FlatBoardJob):
    """Flat board at ``height_mm`` on the stage, a sphere of ``sphere_radius_mm`` on a post and the slot gauge
    with its top ``gauge_height_mm`` above the reference plane, measured with the cell's active calibration
    in the world frame (robot pose and hand-eye): plane height error against the stage, plane residual, the
    flat test of Table 5.1 (per-pixel model only), sphere radius error and fit residual, and the slot depths
    of Fig 5.4 against the gauge's certificate."""

    kind, file_stem, result_file = "validation", "validation", "validation.json"

    def __init__(
        self,
        cfg: CellConfig,
        height_mm: float = 12.5,
        sphere_radius_mm: float = 12.5,
        gauge_height_mm: float = 15.0,
        gauge_certificate: Path = GAUGE_CERTIFICATE,
        **kw: Any,
    ):
        super().__init__(cfg, **kw)
        self.height_mm, self.radius_mm = height_mm, sphere_radius_mm
        self.gauge_height_mm = gauge_height_mm
        self.gauge = load_gauge_certificate(gauge_certificate)

    def plan(self) -> list[View]:
        flat = self.board_view(self.height_mm, index=0, test="plane")
        centre = self.station.point(self.station.board_top_mm + self.radius_mm)
        T_B_T = flange_for_camera(self.cfg, camera_over(self.cfg, centre - (0.0, 0.0, self.radius_mm)))
        sphere = _view(T_B_T, None, None, index=1, test="sphere", centre_W=centre.tolist())
        sphere.data.update(
            board=f"sphere {self.radius_mm:g} mm",
            T_W_Bd=make_pose(np.eye(3), centre).tolist(),
            mesh_path=str(self._sphere_stl()),
        )
        # the gauge stands on the stage, its top gauge_height_mm above the reference plane; the camera looks
        # down at it from where it looks at the flat board (both in the same part of the volume)
        bottom = self.station.point(self.station.board_top_mm + self.gauge_height_mm - self.gauge.top_z_mm)
        gauge = _view(flat.T_B_T, None, None, index=2, test="slots")
        gauge.data.update(
            board=self.gauge.name,
            T_W_Bd=make_pose(np.eye(3), bottom).tolist(),
            mesh_path=str(self.gauge.mesh),
        )
        return [flat, sphere, gauge]

    def _sphere_stl(self) -> Path:
        path = Path.home() / ".cache" / "cell" / f"sphere_{self.radius_mm:g}mm.stl"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            trimesh.creation.icosphere(subdivisions=5, radius=self.radius_mm).export(path)
        return path

    def patterns(self, view: View) -> PatternSet:
        return measuring_patterns(self.cfg.sensor.projector)

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        dec = decode(captured["images"], self.patterns(view), self.cfg.sensor.camera.bit_depth)
        model = active_triangulator(self.cfg)
        cloud = model.triangulate(dec)
        T_W_C = self.cfg.robot.T_W_B.matrix() @ np.asarray(captured["T_B_T"]) @ active_hand_eye(self.cfg)
        pts = transform_points(T_W_C, cloud.points_C[cloud.valid])
        if view.data["test"] == "slots":
            # into the gauge's frame where the stage was asked to put it; its top face only (most of the view,
            # 15 mm above the stage around it; an uncalibrated hand-eye moves it by millimetres)
            pts = transform_points(invert(np.asarray(view.data["T_W_Bd"])), pts)
            pts = pts[np.abs(pts[:, 2] - np.percentile(pts[:, 2], 90)) < 2.0]
        _save_view(out_dir, points_W=pts[:: 4 if view.data["test"] == "plane" else 1])
        summary: dict[str, Any] = {"points": int(len(pts))}
        if view.data["test"] == "plane" and isinstance(model, ReferencePlaneTriangulator):
            # Table 5.1's flat test: heights above the per-pixel model's reference plane (sensor frame only),
            # which holds only if the camera looks at the board from where it saw the reference plane
            summary["flat"] = {
                **flat_test(cloud, model.res_mm, float(view.data["height_mm"])),
                **self._reference_pose_change(np.asarray(captured["T_B_T"])),
            }
        return summary

    def _reference_pose_change(self, T_B_T: Pose) -> dict[str, Any]:
        """How far the flange stands from the pose the sensor calibration saw its reference plane from."""
        sensor = self.cfg.calibration.sensor
        assert sensor is not None  # the validation measures with a sensor file (checked when it starts)
        meta, _ = load_calibration(sensor, "sensor_per_pixel")
        if meta.get("reference_T_B_T") is None:
            return {"reference_pose_change": "unknown (the sensor file does not record it)"}
        dt, dr = _change(T_B_T, np.asarray(meta["reference_T_B_T"]))
        return {"reference_pose_change_mm": dt, "reference_pose_change_deg": dr}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        out: dict[str, Any] = {"points": 0}
        for i, summary in self.view_summaries(run):
            v, pts = views[i], _load_view(run, i)["points_W"]
            out["points"] += len(pts)
            if "flat" in summary:
                out["flat"] = summary["flat"]
            if v.data["test"] == "plane":
                z = np.asarray(v.data["T_W_Bd"])[2, 3]
                on = pts[np.abs(pts[:, 2] - z) < 5.0]
                plane = fit_plane(on)
                out["plane"] = {**plane, "height_error_mm": float(np.median(on[:, 2]) - z)}
            elif v.data["test"] == "slots":
                out["slots"] = {
                    "gauge": {"name": self.gauge.name, "serial": self.gauge.serial},
                    "slots": slot_test(pts, self.gauge.slots),
                }
            else:
                centre = np.asarray(v.data["centre_W"])
                ball = pts[pts[:, 2] > centre[2] - 0.75 * self.radius_mm]
                out["sphere"] = sphere_test(ball, self.radius_mm, centre, band_mm=3.0)
        path = run.path / "validation.json"
        return out, path


# --------------------------------------------------------------------------------------------- runner
def _calibration_folder(
    out: Path,
    cell: Path | None,
    inputs: dict[str, Path] | None = None,
    kind: str = "",
    rerun_finished: bool = True,
) -> tuple[RunFolder, bool]:
    """The run folder ``out`` of a routine of ``kind``: a new one, an unfinished one to resume (True), or a
    finished one whose previous views and checkpoint are moved into ``previous-<time>/`` before a new attempt
    (refused unless ``rerun_finished``). A folder of another kind is refused. ``cell`` and ``inputs`` (name in
    inputs/ -> file) are copied into a new one, and its kind recorded (:meth:`RunFolder.mark_kind`)."""
    out = Path(out)
    if (out / "journal.jsonl").exists():
        run = RunFolder.open(out)
        held = run.kind
        if kind and held is not None and held != kind:
            raise ConfigError(
                f"this folder holds a '{held}' run, not '{kind}'; choose another --out", path=str(out)
            )
        cp = run.load_checkpoint()
        if cp is not None and cp.get("phase") != "done":
            return run, True
        if not rerun_finished:
            raise ConfigError(f"this {kind} run is already done; choose another --out", path=str(out))
        keep = out / f"previous-{time.strftime('%Y%m%dT%H%M%S')}"
        keep.mkdir()
        for name in ("views", "checkpoint.json"):
            if (out / name).exists():
                (out / name).rename(keep / name)
        (out / "views").mkdir()
    else:
        run = RunFolder.create(out.parent, "calibration", name=out.name)
        for name, path in {"cell.yaml": cell, **(inputs or {})}.items():
            if path is not None:
                run.copy_input(path, name)
        run.mark_kind(kind)
    return run, False


def run_routine(
    job: CalibrationJob,
    out: Path,
    cell: Path | None = None,
    *,
    seed: int | None = None,
    on_progress: Callable[[Controller], None] | None = None,
    inputs: dict[str, Path] | None = None,
) -> dict[str, Any]:
    """Run ``job`` under the controller on the cell's devices (with a board stage) into run folder ``out``;
    an unfinished ``out`` is resumed. Returns the result (``job.result_file``); CalibrationError when the
    routine ended paused, faulted or aborted (the message says why; running it again resumes). ``inputs``
    are further files the run reads (copied into its inputs/)."""
    cfg = job.cfg
    run, resume = _calibration_folder(out, cell, inputs, job.kind, job.rerun_finished)
    devices = build_devices(cfg, seed=seed, with_stage=True)
    controller = Controller(
        devices,
        job,
        run,
        ControllerSettings(view_budget=10_000, max_iterations=1),
        robot_limits=RobotLimits.of(cfg.robot),
        home_joints_rad=np.deg2rad(cfg.robot.home_joints_deg),
        motion=JointMotion(UR5E),
        on_progress=on_progress,
    )
    state = controller.execute(resume=resume)
    if state == "paused":
        raise RoutinePaused(
            f"{job.kind} routine paused: {controller.message}; the same command with --out {run.path} "
            "resumes it"
        )
    if state != "done":
        raise CalibrationError(
            f"{job.kind} routine ended '{state}': {controller.message} (run folder {run.path}; run it "
            "again to resume)"
        )
    return json.loads((run.path / job.result_file).read_text())


def handeye_job(
    cfg: CellConfig, method: str = "icp", *, views: int = 12, force: bool = False, seed: int = 1
) -> CalibrationJob:
    """The hand-eye routine by ``method``: ICP of gauge scans against its CAD (``icp``) or AX = XB from
    ``views`` board poses (``tsai``, ``park``, ``daniilidis``)."""
    if method == "icp":
        return HandEyeIcpJob(cfg, force=force, seed=seed)
    if method in ("tsai", "park", "daniilidis"):
        return HandEyeBoardJob(cfg, views=views, method=method, force=force, seed=seed)
    raise ConfigError(
        f"unknown hand-eye method '{method}': use icp, tsai, park or daniilidis", field="method"
    )


def run_validation(
    cell: Path,
    out: Path,
    calibration: Path | None = None,
    gauge: Path | None = None,
    *,
    seed: int = 2,
    **options: Any,
) -> dict[str, Any]:
    """:class:`ValidateJob` of ``cell`` (``options``: its heights and sphere radius) run into ``out``, with
    the sensor ``calibration`` instead of the cell's active one when given, and the slot gauge's certificate
    ``gauge`` (default :data:`GAUGE_CERTIFICATE`) copied into the run; returns validation.json."""
    cfg = load_cell_config(cell)
    if calibration is not None:
        if not calibration.is_file():
            raise ConfigError("sensor calibration file not found; check the path", path=str(calibration))
        cfg.calibration.sensor = calibration.resolve()
    gauge = gauge or GAUGE_CERTIFICATE
    job = ValidateJob(cfg, seed=seed, gauge_certificate=gauge, **options)
    return run_routine(job, out, cell, seed=seed, inputs={"gauge.certificate.yaml": gauge})


ALL_STEPS = ("intrinsics", "projector", "kinematics", "validate")
FIELD = {
    "intrinsics": "intrinsics",
    "projector": "projector",
    "kinematics": "kinematics",
    "handeye": "hand_eye",
    "sensor": "sensor",
    "gamma": "gamma",
}


def calibrate_all(
    cell: Path,
    out: Path,
    *,
    sensor: bool = False,
    seed: int = 1,
    say: Callable[[str], None] = print,
) -> tuple[Path, dict[str, Any]]:
    """Chain the routines into ``out``: intrinsics -> projector -> robot kinematics with the hand-eye from
    board poses -> [per-pixel sensor] -> validation, each in ``out/<step>/`` and each using the calibrations
    before it. Writes ``out/cell.yaml`` (the cell config with its ``calibration:`` section pointing at the new
    files) and ``out/calibration.json``; returns (the cell file, the summary)."""
    cfg = load_cell_config(cell)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    steps: list[tuple[str, Callable[[CellConfig], CalibrationJob]]] = [
        ("intrinsics", lambda c: IntrinsicsJob(c, seed=seed)),
        ("projector", lambda c: ProjectorJob(c, views=12, seed=seed)),
        # the hand-eye found with the kinematics is the one that goes with them: an ICP hand-eye fitted over
        # them doubled the pose-dependent error at the part (0.11 -> 0.22 mm, docs/calibration.md)
        ("kinematics", lambda c: KinematicsJob(c, seed=seed)),
    ]
    if sensor:
        steps.append(("sensor", lambda c: SensorJob(c, seed=seed)))
    steps.append(("validate", lambda c: ValidateJob(c, seed=seed)))
    summary: dict[str, Any] = {}
    for name, make in steps:
        say(f"calibrate {name} -> {out / name}")
        t0 = time.perf_counter()
        result = run_routine(make(cfg), out / name, cell, seed=seed)
        summary[name] = {**result, "seconds": round(time.perf_counter() - t0, 1)}
        if name in FIELD:
            setattr(cfg.calibration, FIELD[name], Path(result["file"]).resolve())
        if name == "kinematics":  # the hand-eye found with the kinematics belongs to them
            cfg.calibration.hand_eye = (out / name / "handeye.yaml").resolve()
    data = yaml.safe_load(Path(cell).read_text())
    data["calibration"] = {k: str(v) for k, v in cfg.calibration.model_dump().items() if v is not None}
    cell_out = out / "cell.yaml"
    cell_out.write_text(yaml.safe_dump(data, sort_keys=False))
    load_cell_config(cell_out)  # the written config must load
    write_json_atomic(
        out / "calibration.json", {"cell": str(cell_out), "source_sha256": _digest(cell), "steps": summary}
    )
    return cell_out, summary


def _digest(path: Path) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def valid_calibration(cell: Path, folder: Path) -> Path | None:
    """``folder/cell.yaml`` when ``folder`` holds a finished `cell calibrate all` of exactly this ``cell``
    file (same content) whose calibrated config loads; else None."""
    summary, cell_out = Path(folder) / "calibration.json", Path(folder) / "cell.yaml"
    if not (summary.exists() and cell_out.exists()):
        return None
    if json.loads(summary.read_text()).get("source_sha256") != _digest(cell):
        return None
    try:
        load_cell_config(cell_out)
    except Exception:  # a calibration file moved or was damaged: calibrate again
        return None
    return cell_out


def ensure_calibration(cell: Path, folder: Path, say: Callable[[str], None] = print) -> Path:
    """The calibrated config of ``cell`` from ``folder``, running `cell calibrate all` there first when it
    holds no valid calibration of it (said through ``say``)."""
    found = valid_calibration(cell, folder)
    if found is not None:
        say(f"using the calibration in {folder} (made for {cell})")
        return found
    say(
        f"no valid calibration of {cell} in {folder}: running `cell calibrate all` there first "
        "(about two minutes)"
    )
    cell_out, _ = calibrate_all(cell, folder, say=say)
    return cell_out
