"""Calibration routines for the technician (dissertation 2.2, 4.1, 5.1.1): per-pixel sensor model, camera and
projector intrinsics, projector response, hand-eye, and the validation tests that judge them."""

from cell.calibration.active import (
    active_gamma_lut,
    active_hand_eye,
    active_kinematics,
    active_measuring_patterns,
    active_sensor_config,
    active_triangulator,
    believed_flange,
    calibration_residual_px,
    calibration_source,
    pose_uncertainty_prior,
    view_pose_prior,
)

__all__ = [
    "active_gamma_lut",
    "active_hand_eye",
    "active_kinematics",
    "active_measuring_patterns",
    "active_sensor_config",
    "active_triangulator",
    "believed_flange",
    "calibration_residual_px",
    "calibration_source",
    "pose_uncertainty_prior",
    "view_pose_prior",
]
