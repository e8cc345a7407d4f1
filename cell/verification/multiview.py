"""The VDI/VDE 2634 Part 3 procedure: the sensor moves between views on the robot, and the long ball bar
(about 300 mm, longer than one view's field) is measured across views and combined in the world frame.

Each bar position lies in the table's plane at the height of the single-view volume's centre; each sphere is
measured from two views (the sensor over the sphere, shifted 40 mm either way along the bar), so the bar spans
four views. Points go to the world with the robot's reported flange pose and the active hand-eye, exactly as
an inspection merges its views, so SD here contains the robot's and the hand-eye's errors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.calibration import calibration_source
from cell.config import CellConfig
from cell.devices import DeviceBundle
from cell.errors import ConfigError
from cell.geometry import invert, look_at, make_pose, transform_points
from cell.planning.kinematics import UR5E
from cell.verification.certificate import Certificate
from cell.verification.figures import FitError
from cell.verification.positions import Volume
from cell.verification.procedure import (
    VOLUME_CENTRE_HEIGHT_MM,
    AcceptanceResult,
    PositionResult,
    SingleView,
    evaluate_ball_bar,
)
from cell.verification.stage import ArtefactStage

BAR_DIRECTIONS_DEG = {"along x": 0.0, "along y": 90.0, "diagonal": 45.0}  # in the table plane
VIEW_SHIFT_MM = 40.0  # each sphere is seen from the view over it shifted this far either way along the bar


def bar_pose(direction_deg: float) -> NDArray[np.float64]:
    """T_W_A of the long bar: centred over the world origin at the volume-centre height, x along the
    direction in the table plane."""
    a = np.deg2rad(direction_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    return make_pose(R, (0.0, 0.0, VOLUME_CENTRE_HEIGHT_MM))


def view_targets(T_W_A: NDArray[np.float64], length_mm: float) -> list[NDArray[np.float64]]:
    """The world points the sensor looks straight down at: two per sphere."""
    axis, centre = T_W_A[:3, 0], T_W_A[:3, 3]
    return [
        centre + axis * (sign * length_mm / 2 + shift)
        for sign in (-1, 1)
        for shift in (-VIEW_SHIFT_MM, VIEW_SHIFT_MM)
    ]


def run_multiview(
    cfg: CellConfig,
    devices: DeviceBundle,
    stage: ArtefactStage,
    certificate: Certificate,
    *,
    directions: dict[str, float] | None = None,
    progress: Any = None,
) -> tuple[AcceptanceResult, dict[str, NDArray[np.float64]]]:
    """Measure the long ball bar in each direction across four views; PF, PS per sphere and SD per position
    against ``verification.mpe_sd_multiview_mm``. Returns the result and each position's world points."""
    bar = certificate.ball_bar_long
    if bar is None:
        raise ConfigError("the certificate has no ball_bar_long (Part 3 needs a bar of about 300 mm)")
    directions = directions if directions is not None else BAR_DIRECTIONS_DEG
    vol = Volume.of(cfg.sensor)
    v = cfg.verification
    result = AcceptanceResult(
        cell=cfg.name,
        geometry_source=calibration_source(cfg),
        volume_mm={
            "width": vol.width_mm,
            "height": vol.height_mm,
            "depth": vol.depth_mm,
            "L0": vol.diagonal_mm,
        },
        mpe_mm={"PF": v.mpe_pf_mm, "PS": v.mpe_ps_mm, "SD": v.mpe_sd_multiview_mm, "F": v.mpe_f_mm},
        positions=[],
        simulated=devices.sim is not None,
        kind="VDI/VDE 2634 Part 3, multi-view (robot-moved sensor)",
        required=("PF", "PS", "SD"),
    )
    sv = SingleView(cfg, devices)
    sv.start()
    T_W_B = cfg.robot.T_W_B.matrix()
    clouds: dict[str, NDArray[np.float64]] = {}
    n_views = 0
    try:
        for k, (label, deg) in enumerate(directions.items()):
            label = f"long ball bar, {label}"
            if progress is not None:
                progress(k, len(directions), label)
            T_W_A = bar_pose(deg)
            stage.place("ball_bar_long", T_W_A, label)
            merged = []
            for target in view_targets(T_W_A, bar.centre_distance_mm):
                T_W_C = look_at(target + (0.0, 0.0, cfg.sensor.standoff_mm), target, up=(0.0, 1.0, 0.0))
                T_B_T = invert(T_W_B) @ T_W_C @ invert(sv.T_T_C)
                q = UR5E.ik_nearest(T_B_T, devices.robot.joints())
                devices.robot.move_joint(q, cfg.robot.max_joint_speed_rad_s, cfg.robot.max_joint_accel_rad_s2)
                merged.append(transform_points(sv.T_W_C_model(), sv.measure(n_views)))
                n_views += 1
            points_W = np.vstack(merged)
            clouds[label] = points_W
            try:
                r = evaluate_ball_bar(points_W, T_W_A, bar)
            except FitError as exc:
                r = PositionResult(label, "ball_bar_long", error=f"too few points on the artefact: {exc}")
            r.label, r.artefact = label, "ball_bar_long"
            result.positions.append(r)
        stage.clear()
    finally:
        sv.stop()
    result.summarise()
    return result, clouds
