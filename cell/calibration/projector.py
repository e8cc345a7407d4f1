"""Projector calibration for the pinhole model (Moreno & Taubin, "Simple, accurate, and robust
projector-camera calibration", 3DIMPVT 2012): the projector is calibrated as an inverse camera.

Per board view, structured light decoded on the board gives the projector coordinate (u, v) of every lit
camera pixel. Around each detected ChArUco corner, a local homography from camera pixels to projector pixels
is fitted to the decoded pixels of a small window (the board is planar, so the map is a homography up to the
lens distortion, which is negligible over the window) and the corner's projector position is the homography
applied to its camera position: sub-pixel, and independent of the code's quantisation. cv2.calibrateCamera on
(board corner, projector position) pairs gives a first projector model.

Moreno and Taubin then fix both lenses and fit only the camera-to-projector transform (cv2.stereoCalibrate,
CALIB_FIX_INTRINSIC). Calibrated alone, on board poses of its own, the projector's lens is poorly determined
(the board fills the middle of the projector's image only): in the honest simulated world its principal point
came out 5 px off and its fx and fy 0.13 % apart, and the transform fitted to that lens and the camera's left
the triangulation out of scale, the ball bar's SD at +35 um (docs/calibration.md, "The scale of the sensor").
So by default the last step is one bundle adjustment of the pair instead (cv2.stereoCalibrate with
CALIB_USE_INTRINSIC_GUESS): both lenses, the transform and the board poses, each board pose held by what both
devices saw of it. It refines the camera's lens too (its focal length 0.02 % off after the camera routine
alone, 0.005 % after this), so the result carries the camera it belongs to (``K_cam``, ``dist_cam``): camera
rays and projector planes are consistent only as a pair, and the active calibration uses them together
(cell.calibration.active).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.calibration.intrinsics import MIN_CORNERS, MIN_VIEWS, CharucoView, CornerBoard
from cell.errors import CalibrationError
from cell.geometry import Pose, invert, make_pose

JOINT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass
class ProjectorCalibration:
    """Projector intrinsics (K, distortion; projector pixels) and its pose in the camera frame T_C_P (mm),
    the camera lens it belongs to (``K_cam``, ``dist_cam``: refined with it, or the one given), and the RMS
    reprojection errors of the projector alone and of the stereo fit (px)."""

    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    size: tuple[int, int]
    T_C_P: Pose
    rms_px: float
    stereo_rms_px: float
    views: int
    corners: int
    K_cam: NDArray[np.float64]
    dist_cam: NDArray[np.float64]


def corners_in_projector(
    view: CharucoView, u: NDArray, v: NDArray, half_window: int = 15, min_pixels: int = 50
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Projector position (N, 2) of every corner of ``view`` by a local homography (least squares over the
    window's decoded pixels), and which corners had enough decoded pixels around them.

    ``u``, ``v``: decoded projector column and row maps (H, W), NaN where invalid. One cv2.findHomography per
    corner (a few dozen per view), each over a (2*half_window+1)^2 window."""
    H, W = u.shape
    out = np.full((len(view.ids), 2), np.nan)
    ok = np.zeros(len(view.ids), bool)
    off = np.arange(-half_window, half_window + 1)
    dy, dx = np.meshgrid(off, off, indexing="ij")
    for i, (x, y) in enumerate(view.corners_px):
        ys, xs = int(round(y)) + dy.ravel(), int(round(x)) + dx.ravel()
        inside = (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
        ys, xs = ys[inside], xs[inside]
        uu, vv = u[ys, xs], v[ys, xs]
        good = np.isfinite(uu) & np.isfinite(vv)
        if good.sum() < min_pixels:
            continue
        src = np.column_stack([xs[good], ys[good]]).astype(np.float64)
        dst = np.column_stack([uu[good], vv[good]]).astype(np.float64)
        Hm, _ = cv2.findHomography(src, dst, 0)
        if Hm is None:
            continue
        out[i] = cv2.perspectiveTransform(np.array([[[x, y]]], np.float64), Hm).reshape(2)
        ok[i] = True
    return out, ok


def calibrate_projector(
    views: Sequence[CharucoView],
    projector_px: Sequence[NDArray],
    valid: Sequence[NDArray],
    board: CornerBoard,
    K_cam: NDArray,
    dist_cam: NDArray,
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    fix_k3: bool = True,
    joint: bool = True,
) -> ProjectorCalibration:
    """Projector K, distortion and T_C_P from board views with the corners' projector positions
    (:func:`corners_in_projector`) and the calibrated camera (``K_cam``, ``dist_cam``: the start of the
    camera's lens). ``joint`` (default): one bundle adjustment of both lenses, the transform and the board
    poses (see the module's note), the camera refined with it; False: Moreno and Taubin's fit as published
    (the projector's lens from its own views, both lenses fixed for the transform, the camera as given)."""
    obj, img_c, img_p = [], [], []
    for view, pp, ok in zip(views, projector_px, valid, strict=True):
        if ok.sum() < MIN_CORNERS:
            continue
        obj.append(view.object_points(board)[ok].astype(np.float32).reshape(-1, 1, 3))
        img_c.append(view.corners_px[ok].astype(np.float32).reshape(-1, 1, 2))
        img_p.append(pp[ok].astype(np.float32).reshape(-1, 1, 2))
    if len(obj) < MIN_VIEWS:
        raise CalibrationError(
            f"projector calibration: {len(obj)} board views with >= {MIN_CORNERS} decoded "
            f"corners, at least {MIN_VIEWS} are needed; is the projector lighting the board?"
        )
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    K_c: NDArray = np.asarray(K_cam, np.float64)
    d_c: NDArray = np.asarray(dist_cam, np.float64)
    rms, K_p, dist_p, _, _ = cv2.calibrateCamera(obj, img_p, projector_size, None, None, flags=flags)
    if joint:
        stereo = cv2.stereoCalibrate(
            obj,
            img_c,
            img_p,
            K_c.copy(),
            d_c.copy(),
            K_p,
            dist_p,
            camera_size,
            flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags,
            criteria=JOINT_CRITERIA,
        )
        K_c, d_c, K_p, dist_p = stereo[1], stereo[2], stereo[3], stereo[4]
    else:
        stereo = cv2.stereoCalibrate(
            obj, img_c, img_p, K_c, d_c, K_p, dist_p, camera_size, flags=cv2.CALIB_FIX_INTRINSIC
        )
    stereo_rms, R, T = stereo[0], stereo[5], stereo[6]
    T_P_C = make_pose(R, np.asarray(T).ravel())  # stereoCalibrate: x_P = R x_C + T
    return ProjectorCalibration(
        K_p,
        dist_p.ravel()[:5].astype(np.float64),
        projector_size,
        invert(T_P_C),
        float(rms),
        float(stereo_rms),
        len(obj),
        int(sum(len(o) for o in obj)),
        np.asarray(K_c, np.float64),
        np.ravel(d_c)[:5].astype(np.float64),
    )
