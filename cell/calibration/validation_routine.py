"""The validation routine as a controller job: the flat test, a sphere and the slot gauge measured with the
cell's active calibration (dissertation Table 5.1, Fig 5.4)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cell.calibration.active import active_hand_eye, active_measuring_patterns, active_triangulator
from cell.calibration.handeye import pose_error
from cell.calibration.procedures import (
    GAUGE_CERTIFICATE,
    _view,
    camera_over,
    flange_for_camera,
    load_view_arrays,
    save_view_arrays,
)
from cell.calibration.sensor_routines import FlatBoardJob
from cell.calibration.store import load_calibration
from cell.calibration.validation import (
    fit_plane,
    flat_test,
    load_gauge_certificate,
    slot_test,
    sphere_mesh_lsq,
    sphere_test,
)
from cell.config import CellConfig
from cell.geometry import Pose, invert, make_pose, transform_points
from cell.run_data import View
from cell.runs import RunFolder
from cell.sensing.decode import decode
from cell.sensing.patterns import PatternSet
from cell.sensing.triangulate import ReferencePlaneTriangulator


# --------------------------------------------------------------------------------------------- validation
class ValidateJob(FlatBoardJob):
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
        """The sphere's CAD, as the verification artefacts' (least-squares radius ``radius_mm``, facets within
        +-0.6 um), written once to the user's cache (the name says which mesh: an older file held an icosphere
        whose surface lay 2.3 um inside the radius)."""
        name = f"sphere_{self.radius_mm:g}mm_lsq_ico6.stl"
        path = Path.home() / ".cache" / "cell" / name
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            sphere_mesh_lsq(self.radius_mm, subdivisions=6).export(path)
        return path

    def patterns(self, view: View) -> PatternSet:
        return active_measuring_patterns(self.cfg)  # through the gamma LUT, if any

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
        save_view_arrays(out_dir, points_W=pts[:: 4 if view.data["test"] == "plane" else 1])
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
        dt, dr = pose_error(T_B_T, np.asarray(meta["reference_T_B_T"]))
        return {"reference_pose_change_mm": dt, "reference_pose_change_deg": dr}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        out: dict[str, Any] = {"points": 0}
        for i, summary in self.view_summaries(run):
            v, pts = views[i], load_view_arrays(run, i)["points_W"]
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
