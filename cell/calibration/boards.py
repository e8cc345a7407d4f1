"""The board pose in the camera from detected corners (cv2.solvePnP); the boards' corner grids are
:class:`cell.calibration.capture_folder.ChessboardTarget` and OpenCV's ChArUco board."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.errors import CalibrationError
from cell.geometry import Pose, make_pose


def board_pose_from_corners(object_mm: NDArray, image_px: NDArray, K: NDArray, dist: NDArray) -> Pose:
    """``T_C_Bd``: board frame in the camera frame from >= 4 corner correspondences (iterative PnP, mm)."""
    obj = np.asarray(object_mm, dtype=np.float64).reshape(-1, 1, 3)
    img = np.asarray(image_px, dtype=np.float64).reshape(-1, 1, 2)
    if len(obj) < 4 or len(obj) != len(img):
        raise CalibrationError(f"board pose needs >= 4 matched corners, got {len(obj)} and {len(img)}")
    ok, rvec, tvec = cv2.solvePnP(
        obj, img, np.asarray(K, float), np.asarray(dist, float), flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok:
        raise CalibrationError("board pose: solvePnP found no solution; is the board in view and flat?")
    return make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
