"""Camera intrinsics from views of a ChArUco board (OpenCV's CharucoDetector and calibrateCamera).

Each view gives the sub-pixel image positions of the board's inner chessboard corners, identified by the ArUco
markers between them (so partial views count). The detector's own sub-pixel step (cornerSubPix on the raw
image, stopping at 0.1 px) leaves errors of ~0.05 px that follow each corner's position within its pixel
(pixel locking: a sharp, barely sampled edge tells little about where in the pixel it lies), so the corners
are refined again (:func:`refine_corners`: cornerSubPix on the image smoothed by a Gaussian of about one
pixel, to 0.001 px), which halves that error. cv2.calibrateCamera fits K and Brown-Conrady distortion
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
from scipy.spatial import cKDTree

from cell.errors import CalibrationError
from cell.geometry import Pose, make_pose

MIN_VIEWS = 4
MIN_CORNERS = 8
REFINE_SIGMA_PX = 1.2  # Gaussian smoothing before the sub-pixel step (pixel locking: docs/calibration.md)
REFINE_HALF_WINDOW_PX = 6  # cornerSubPix half window, at most; less where the markers come closer
REFINE_STOP_PX = 0.001
REFINE_MARGIN_PER_SIGMA = 6.0  # the smoothing at most the view's median marker margin / 6 (window >= 4 sigma)
REFINE_MAX_MOVE_PX = 1.0  # a corner the refinement moves farther than this from the detector's is dropped


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
    (px) over all corners and per view, each view's board pose T_C_Bd (mm), and the fit's stated standard
    deviations of fx, fy, cx, cy (px; OpenCV's stdDeviationsIntrinsics: residuals and Jacobian)."""

    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    size: tuple[int, int]
    rms_px: float
    view_rms_px: NDArray[np.float64]
    T_C_Bd: list[Pose] = field(default_factory=list)
    sd_K_px: NDArray[np.float64] = field(default_factory=lambda: np.full(4, np.nan))


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
    view = refine_corners(
        image, CharucoView(corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int32)), board
    )
    return view if len(view.ids) >= min_corners else None


def refine_corners(
    image: NDArray,
    view: CharucoView,
    board: cv2.aruco.CharucoBoard,
    sigma_px: float = REFINE_SIGMA_PX,
    half_window_px: int = REFINE_HALF_WINDOW_PX,
) -> CharucoView:
    """The chessboard corners of ``view`` located again on ``image`` (the original grey levels, any depth):
    cv2.cornerSubPix on the image smoothed by a Gaussian of ``sigma_px``, iterated to 0.001 px.

    Why: the simulated camera samples its pixels' centres and a real one integrates a pixel's area, but both
    see a sharp edge over one or two pixels, and a gradient-based corner then locks toward pixel borders
    (measured on the simulator's board images against the true projections: +0.027 px for corners in the
    first half of a pixel, -0.017 px in the second, 0.056 px RMS without any noise: bench/trace_intrinsics).
    Smoothing first spreads the edge over enough pixels for the gradients to place it (0.027 px RMS on the
    same images, 0.032 px with the camera's noise); a point-symmetric blur does not move the saddle of a
    chessboard corner. The window stays clear of the ArUco markers: each corner's half window is
    at most the marker's margin in the image (from the distance to the nearest other corner, which under
    perspective is the shorter side of a square) less twice the smoothing, and the smoothing at most a sixth
    of the view's median margin, so that the window spans at least 4 sigma (small, far or steep boards, binned
    cameras: at a quarter, the binned camera's 5 px margins left a 2 px window on a 1.2 px blur, and its
    corners fitted worse than the detector's own, 0.062 against 0.049 px RMS, principal point 1.1 px off the
    truth over 5 seeds against 0.7; at a sixth, 0.043 px RMS and 0.6 px). A corner whose margin leaves no
    window of 2 px keeps the detector's position; one the refinement moves more than 1 px is dropped."""
    n = len(view.ids)
    if n < 2:
        return view
    pts = view.corners_px
    distances, _ = cKDTree(pts).query(pts, k=2)
    nearest = np.asarray(distances, np.float64)[:, 1]  # to the nearest other corner
    margin = nearest * (board.getSquareLength() - board.getMarkerLength()) / (2 * board.getSquareLength())
    sigma = min(sigma_px, float(np.median(margin)) / REFINE_MARGIN_PER_SIGMA)
    half = np.minimum(np.floor(margin - 2 * sigma), half_window_px).astype(int)
    grey = cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), sigma)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, REFINE_STOP_PX)
    out = pts.copy()
    for w in np.unique(half[half >= 2]):
        sel = half == w
        c = pts[sel].astype(np.float32).reshape(-1, 1, 2)
        out[sel] = cv2.cornerSubPix(grey, c, (int(w), int(w)), (-1, -1), crit).reshape(-1, 2)
    keep = np.linalg.norm(out - pts, axis=1) <= REFINE_MAX_MOVE_PX
    return CharucoView(out[keep], view.ids[keep])


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
    rms, K, dist, rvecs, tvecs, sd_intr, _, _ = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
        obj,
        img,
        size,
        None,
        None,
        flags=flags,  # (the stubs do not allow None, which calibrateCamera's do)
    )
    poses = [make_pose(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs, strict=True)]
    per_view = np.array(
        [_view_rms(o, i, r, t, K, dist) for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True)]
    )
    return Intrinsics(
        np.asarray(K, np.float64),
        dist.ravel()[:5].astype(np.float64),
        size,
        float(rms),
        per_view,
        poses,
        np.asarray(sd_intr, np.float64).ravel()[:4],
    )


def _view_rms(obj: NDArray, img: NDArray, rvec: NDArray, tvec: NDArray, K: NDArray, dist: NDArray) -> float:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj - img).reshape(-1, 2) ** 2, axis=1))))
