"""Camera intrinsics from views of a ChArUco board (OpenCV's CharucoDetector and calibrateCamera).

Each view gives the sub-pixel image positions of the board's inner chessboard corners, identified by the ArUco
markers between them (so partial views count); cv2.calibrateCamera fits K and Brown-Conrady distortion
(k1, k2, p1, p2; k3 stays 0 unless asked, as it is poorly determined over a 200 mm field and the usual cause
of wild extrapolation at the corners) and returns the board pose T_C_Bd of every view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cell.errors import CalibrationError
from cell.geometry import Pose, make_pose

MIN_VIEWS = 4
MIN_CORNERS = 8


class CornerBoard(Protocol):
    """What the calibrations read of a board: its inner corners in the board frame {Bd} (N, 3), mm, by id.
    A cv2.aruco.CharucoBoard, or a plain chessboard (cell.calibration.capture_folder.ChessboardTarget)."""

    def getChessboardCorners(self) -> ArrayLike: ...  # the cv2.aruco.CharucoBoard method name


@dataclass
class CharucoView:
    """Detected inner corners of one board view: image positions (N, 2) px and their board ids (N,)."""

    corners_px: NDArray[np.float64]
    ids: NDArray[np.int32]

    def object_points(self, board: CornerBoard) -> NDArray[np.float64]:
        """The same corners in the board frame {Bd} (N, 3), mm."""
        return np.asarray(board.getChessboardCorners(), np.float64)[self.ids]


@dataclass
class Intrinsics:
    """A calibrated pinhole camera: K (3x3, px), distortion (k1, k2, p1, p2, k3), the RMS reprojection error
    (px) over all corners and per view, and each view's board pose T_C_Bd (mm)."""

    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    size: tuple[int, int]
    rms_px: float
    view_rms_px: NDArray[np.float64]
    T_C_Bd: list[Pose] = field(default_factory=list)


def detect_charuco(
    image: NDArray, board: cv2.aruco.CharucoBoard, min_corners: int = MIN_CORNERS
) -> CharucoView | None:
    """Inner corners of ``board`` in ``image`` (8/16-bit grey), or None when fewer than ``min_corners``."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(img)
    if ids is None or len(ids) < min_corners:
        return None
    return CharucoView(corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int32))


def calibrate_intrinsics(
    views: Sequence[CharucoView], board: CornerBoard, size: tuple[int, int], fix_k3: bool = True
) -> Intrinsics:
    """K and distortion of a camera of ``size`` (width, height) px from >= 4 detected board views."""
    good = [v for v in views if v is not None and len(v.ids) >= MIN_CORNERS]
    if len(good) < MIN_VIEWS:
        raise CalibrationError(
            f"camera intrinsics: the board was found in {len(good)} views, at least "
            f"{MIN_VIEWS} are needed; check lighting, focus and that the board is in view"
        )
    obj = [v.object_points(board).astype(np.float32).reshape(-1, 1, 3) for v in good]
    img = [v.corners_px.astype(np.float32).reshape(-1, 1, 2) for v in good]
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
    poses = [make_pose(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs, strict=True)]
    per_view = np.array(
        [_view_rms(o, i, r, t, K, dist) for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True)]
    )
    return Intrinsics(
        np.asarray(K, np.float64), dist.ravel()[:5].astype(np.float64), size, float(rms), per_view, poses
    )


def _view_rms(obj: NDArray, img: NDArray, rvec: NDArray, tvec: NDArray, K: NDArray, dist: NDArray) -> float:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj - img).reshape(-1, 2) ** 2, axis=1))))
