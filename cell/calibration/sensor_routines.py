"""The routines that calibrate the sensor itself as controller jobs: camera and projector intrinsics from
ChArUco board poses, the projector's response (gamma) and the per-pixel sensor model (dissertation 5.1)
from the flat board on the stage."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cell.calibration.active import active_sensor_config
from cell.calibration.gamma import gamma_figures, grey_levels, linearising_lut, measure_response
from cell.calibration.intrinsics import CharucoView, calibrate_intrinsics
from cell.calibration.procedures import (
    CHARUCO,
    FLAT,
    CalibrationJob,
    _view,
    camera_over,
    charuco,
    charuco_poses,
    detect_board,
    flange_for_camera,
    load_view_arrays,
    save_view_arrays,
)
from cell.calibration.projector import calibrate_projector, corners_in_projector
from cell.calibration.store import load_calibration, save_calibration
from cell.config import CellConfig
from cell.geometry import make_pose
from cell.run_data import View
from cell.runs import RunFolder
from cell.sensing.decode import decode
from cell.sensing.patterns import (
    PatternSet,
    projector_calibration_patterns,
    sensor_calibration_patterns,
    uniform_patterns,
)


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
        found = detect_board(view, captured["images"][0])
        save_view_arrays(out_dir, corners_px=found.corners_px, ids=found.ids)
        return {"corners": int(len(found.ids))}

    def _charuco_views(self, run: RunFolder) -> list[CharucoView]:
        return [
            CharucoView(d["corners_px"], d["ids"])
            for d in map(lambda i: load_view_arrays(run, i), run.completed_views())
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
            "K_sd_px": res.sd_K_px.tolist(),  # the fit's standard deviations of fx, fy, cx, cy
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
            made_for=self.made_for,
        )
        return figs, path


# --------------------------------------------------------------------------------------------- projector
class ProjectorJob(IntrinsicsJob):
    """Projector K and T_C_P (Moreno-Taubin): GCPS in both directions on the ChArUco board, a local homography
    per corner, calibrateCamera for the projector, then one bundle adjustment of camera and projector
    (stereoCalibrate, cell.calibration.projector). The camera it starts from is the cell's active one
    (calibration.intrinsics) unless ``intrinsics`` names a file; the file holds the camera lens refined with
    the projector (``camera_K``, ``camera_dist``), which the active calibration then uses."""

    kind, file_stem = "projector", "projector"

    def __init__(self, cfg: CellConfig, views: int = 6, intrinsics: Path | None = None, **kw: Any) -> None:
        super().__init__(cfg, views=views, **kw)
        self.intrinsics = intrinsics

    def patterns(self, view: View) -> PatternSet:
        return projector_calibration_patterns(self.cfg.sensor.projector)

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        images = captured["images"]
        found = detect_board(view, images[0])
        ps = self.patterns(view)
        dec = decode(images, ps, self.cfg.sensor.camera.bit_depth)
        pp, ok = corners_in_projector(found, dec.axes["columns"].u, dec.axes["rows"].u)
        save_view_arrays(out_dir, corners_px=found.corners_px, ids=found.ids, proj_px=pp, ok=ok)
        return {"corners": int(len(found.ids)), "decoded_corners": int(ok.sum())}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        cam, proj = self.cfg.sensor.camera, self.cfg.sensor.projector
        active = active_sensor_config(self.cfg).camera
        K, dist = active.K(), active.distortion.as_array()
        if self.intrinsics is not None:
            _, arrays = load_calibration(self.intrinsics, "camera_intrinsics")
            K, dist = arrays["K"], arrays["dist"]
        data = [load_view_arrays(run, i) for i in run.completed_views()]
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
            "camera_K": res.K_cam.tolist(),
            "camera_dist": res.dist_cam.tolist(),
        }
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {
                "K": res.K,
                "dist": res.dist,
                "T_C_P": res.T_C_P,
                "camera_K": res.K_cam,
                "camera_dist": res.dist_cam,
            },
            {
                "projector": {"serial": proj.serial, "resolution": [proj.width_px, proj.height_px]},
                "camera": {"serial": cam.serial, "resolution": [cam.width_px, cam.height_px]},
                "figures": figs,
                "quality": {"rms_px": res.stereo_rms_px},
            },
            "quality.rms_px",
            self.force,
            made_for=self.made_for,
        )
        return figs, path


# --------------------------------------------------------------------------------------------- flat board
class FlatBoardJob(CalibrationJob):
    """Routines on the flat white board under a camera looking straight down at it."""

    def board_view(self, height_mm: float, **extra: Any) -> View:
        top = self.station.point(self.station.board_top_mm)
        T_B_T = flange_for_camera(self.cfg, camera_over(self.cfg, top))
        return _view(
            T_B_T, FLAT, make_pose(np.eye(3), top + (0.0, 0.0, height_mm)), height_mm=height_mm, **extra
        )


class GammaJob(FlatBoardJob):
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
        save_view_arrays(out_dir, response=response)
        return {"levels": len(self.levels)}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        response = load_view_arrays(run, run.completed_views()[0])["response"]
        figs = {**gamma_figures(self.levels, response), "points": len(self.levels)}
        path = save_calibration(
            run.path / self.file_stem,
            self.kind,
            {"lut": linearising_lut(self.levels, response)},
            {"projector": {"name": self.cfg.sensor.projector.name}, "figures": figs},
            force=self.force,
            made_for=self.made_for,
        )
        return figs, path


class SensorJob(FlatBoardJob):
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
        save_view_arrays(out_dir, u=u.astype(np.float32), v=v.astype(np.float32))
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
            d = load_view_arrays(run, i)
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
            made_for=self.made_for,
        )
        return {**res.figures, "points": int(len(res.points_px))}, path


# --------------------------------------------------------------------------------------------- hand-eye
