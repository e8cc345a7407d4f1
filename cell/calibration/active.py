"""The calibration the inspection job measures with: the files named in the cell config's ``calibration:``
section, or the config's nominal geometry when none is set."""

from __future__ import annotations

import numpy as np

from cell.calibration.sensor import load_sensor_model
from cell.calibration.store import load_calibration
from cell.config import CellConfig
from cell.errors import ConfigError
from cell.geometry import Pose
from cell.sensing.triangulate import PinholeTriangulator, Triangulator


def active_triangulator(cfg: CellConfig) -> Triangulator:
    """The calibrated per-pixel reference-plane model when ``cfg.calibration.sensor`` is set (checked against
    the camera's resolution), else the pinhole model from the config's camera/projector geometry."""
    if cfg.calibration.sensor is not None:
        return load_sensor_model(cfg.calibration.sensor, cfg.sensor.camera)
    return PinholeTriangulator.from_sensor(cfg.sensor)


def active_hand_eye(cfg: CellConfig) -> Pose:
    """``T_T_C`` (4x4, mm): the hand-eye calibration file when ``cfg.calibration.hand_eye`` is set, else the
    configured ``sensor.T_T_C`` (the mounting drawing)."""
    if cfg.calibration.hand_eye is None:
        return cfg.sensor.T_T_C.matrix()
    _, arrays = load_calibration(cfg.calibration.hand_eye, "hand_eye")
    T = np.asarray(arrays["T_T_C"], dtype=np.float64)
    if (
        T.shape != (4, 4)
        or not np.allclose(T[3], (0, 0, 0, 1))
        or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    ):
        raise ConfigError(
            "hand-eye file holds no rigid 4x4 T_T_C", path=str(cfg.calibration.hand_eye), field="T_T_C"
        )
    return T
