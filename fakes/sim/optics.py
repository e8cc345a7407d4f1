"""Pinhole optics of the simulated camera (Brown distortion) and projector (no distortion); thin-lens blur.

Frames follow OpenCV: +z forward, +x right, +y down; pixel (u, v) = (column, row) and integer coordinates are
pixel centres. Lengths in mm.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.config import CameraConfig, PinholeConfig, ProjectorConfig

# cv2.undistortPoints iterates a fixed-point scheme; 20 iterations bring the reprojection of each pixel centre
# of the prototype lens (k1=-0.08, k2=0.12) back to the pixel within 1e-12 px (5 leave ~1e-9 px).
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-15)


def _distortion(cfg: PinholeConfig) -> NDArray[np.float64]:
    return cfg.distortion.as_array() if isinstance(cfg, CameraConfig) else np.zeros(5)


def pixel_rays(cfg: PinholeConfig) -> NDArray[np.float64]:
    """Unit ray directions (H, W, 3) in the optical frame through every pixel centre, distortion removed.

    Cached per intrinsics (the same lens renders every pose); the returned array is read-only.
    """
    return _pixel_rays(
        cfg.width_px, cfg.height_px, cfg.fx_px, cfg.fy_px, cfg.cx_px, cfg.cy_px, tuple(_distortion(cfg))
    )


@lru_cache(maxsize=4)
def _pixel_rays(
    w: int, h: int, fx: float, fy: float, cx: float, cy: float, dist: tuple[float, ...]
) -> NDArray[np.float64]:
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    if any(dist):
        xy = np.asarray(
            cv2.undistortPoints(pts, K, np.asarray(dist), None, None, None, _UNDISTORT_CRITERIA), np.float64
        ).reshape(-1, 2)
    else:
        xy = (pts.reshape(-1, 2) - (cx, cy)) / (fx, fy)
    rays = np.column_stack([xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays = rays.reshape(h, w, 3)
    rays.setflags(write=False)
    return rays


def project_points(
    cfg: PinholeConfig, points: NDArray[np.float64], distortion: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Pixel coordinates (..., 2) of points (..., 3) given in the device's optical frame (mm).

    Brown distortion for a camera (cv2.projectPoints semantics), plain pinhole for a projector unless
    ``distortion`` (OpenCV order) gives its lens (the simulated world's projector). Points with z <= 0 (behind
    the device) come back as NaN.
    """
    p = np.asarray(points, dtype=np.float64)
    shape = p.shape[:-1]
    p = p.reshape(-1, 3)
    out = np.full((len(p), 2), np.nan)
    front = p[:, 2] > 0
    if np.any(front):
        dist = _distortion(cfg) if distortion is None else np.asarray(distortion, dtype=np.float64)
        q = p[front]
        x, y = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
        if np.any(dist):
            # OpenCV's 5-coefficient Brown model written out: cv2.projectPoints took 1.1 s per megapixel
            # here, this takes ~0.1 s (tests/test_sim_geometry.py compares the two)
            k1, k2, p1, p2, k3 = dist
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = (
                x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
            )
        out[front, 0] = cfg.fx_px * x + cfg.cx_px
        out[front, 1] = cfg.fy_px * y + cfg.cy_px
    return out.reshape(*shape, 2)


def blur_sigma_px(cfg: PinholeConfig, depth_mm: NDArray[np.floating]) -> NDArray[np.float32]:
    """Gaussian sigma (pixels of this device) of the defocus blur of a point at ``depth_mm`` along the axis.

    Thin lens focused at s with focal length f and f-number N: the blur circle on the sensor/DMD has diameter
    c = f^2 / N * |z - s| / (z (s - f)). A uniform disc of diameter c has a per-axis standard deviation of
    c / 4, which is the Gaussian we substitute for it.
    """
    f = cfg.focal_length_mm
    s = cfg.focus_distance_mm
    z = np.maximum(np.asarray(depth_mm, dtype=np.float64), f * 1.001)
    c_mm = f * f / cfg.f_number * np.abs(z - s) / (z * (s - f))
    return (c_mm / (cfg.pixel_pitch_um * 1e-3) / 4.0).astype(np.float32)


def projector_response(proj: ProjectorConfig, level: Any) -> Any:
    """Relative radiance (0..1) of the projector at grey ``level`` (0..1, scalar or array): the black level it
    leaks plus the rest along its gamma curve: the scene and board renderers' response. (The simulated DLP
    camera exposure, fakes/camera.py, splits a grey level into bit planes along the same gamma without the
    black level, which every plane leaks alike.)"""
    return proj.black_level + (1 - proj.black_level) * np.asarray(level, dtype=np.float64) ** proj.gamma


def projector_lut(proj: ProjectorConfig) -> NDArray[np.float32]:
    """:func:`projector_response` of the 256 grey levels of an 8-bit image."""
    return projector_response(proj, np.arange(256) / 255.0).astype(np.float32)
