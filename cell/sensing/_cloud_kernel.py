"""Compiled pinhole ray/plane triangulation into an organised cloud (numba, parallel over rows), and the
projector lens's Brown-Conrady projection of points (:func:`project_axis`).

Written by hand because the NumPy form of the same per-pixel formula made ~10 full-image float64
temporaries (0.23 s at 2448x2048); one fused pass writes the float32 cloud directly. Arithmetic is the
NumPy version's, in float64 per pixel, so the points are bit-identical to it. ``project_axis`` is
cv2.projectPoints' model (k1, k2, p1, p2, k3; no skew) for one image axis: OpenCV computes the full Jacobian
with every projection (15 doubles a coordinate: 1.2 GB and seconds for a 5 MP view's points).
"""

from __future__ import annotations

import numba as nb
import numpy as np

_INCONSISTENT = 8


@nb.njit(cache=True, parallel=True, nogil=True)
def pinhole_cloud(u, reasons_in, xn, yn, f, c, Rk, R2, tk, t2):
    """Points (H, W, 3) float32 in {C} (mm) and reasons: pixel ray X = z (x_n, y_n, 1) meets the projector
    plane of coordinate ``u`` (normal Rk - a R2 in {C}, a = (u - c) / f, through the projector centre with
    ``tk`` = Rk.t, ``t2`` = R2.t). Pixels with no valid intersection (z not finite or <= 0) become
    INCONSISTENT.
    """
    H, W = u.shape
    pts = np.empty((H, W, 3), np.float32)
    reasons = np.empty((H, W), np.uint8)
    nan = np.float32(np.nan)
    for r in nb.prange(H):
        for col in range(W):
            x, y = xn[r, col], yn[r, col]
            a = (np.float64(u[r, col]) - c) / f
            rk = Rk[0] * x + Rk[1] * y + Rk[2]
            r2 = R2[0] * x + R2[1] * y + R2[2]
            z = (tk - a * t2) / (rk - a * r2)
            b = reasons_in[r, col]
            if b == 0 and not (np.isfinite(z) and z > 0):
                b = _INCONSISTENT
            reasons[r, col] = b
            if b == 0:
                pts[r, col, 0] = np.float32(z * x)
                pts[r, col, 1] = np.float32(z * y)
                pts[r, col, 2] = np.float32(z)
            else:
                pts[r, col, 0] = nan
                pts[r, col, 1] = nan
                pts[r, col, 2] = nan
    return pts, reasons


@nb.njit(cache=True, parallel=True, nogil=True)
def project_axis(P, fx, fy, cx, cy, dist, axis):
    """Image coordinate along ``axis`` (0: u, 1: v; pixels) of points ``P`` (N, 3) in the lens's frame
    through a pinhole with Brown-Conrady distortion ``dist`` = (k1, k2, p1, p2, k3), as cv2.projectPoints
    computes it with zero rotation and translation."""
    out = np.empty(P.shape[0], np.float64)
    for i in nb.prange(P.shape[0]):
        out[i] = _project(P[i, 0], P[i, 1], P[i, 2], fx, fy, cx, cy, dist, axis)
    return out


@nb.njit(cache=True, parallel=True, nogil=True)
def lens_step(pts, reasons, u_plane, u_decoded, R, t, fx, fy, cx, cy, dist, axis):
    """One Newton step of the column each valid pixel's pinhole plane uses (float32, as ``u_plane``): the
    point triangulated with ``u_plane`` (``pts`` (H, W, 3) float32 in {C}, valid where ``reasons`` is 0) is
    projected through the lens from the projector at ``R``, ``t`` (``T_P_C``), and the column moves by what
    the lens added (``u_decoded`` minus the projection); other pixels keep their column."""
    H, W = u_plane.shape
    out = np.empty((H, W), np.float32)
    for r in nb.prange(H):
        for c in range(W):
            out[r, c] = u_plane[r, c]
            if reasons[r, c] == 0:
                x, y, z = np.float64(pts[r, c, 0]), np.float64(pts[r, c, 1]), np.float64(pts[r, c, 2])
                px = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
                py = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
                pz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
                seen = np.float32(_project(px, py, pz, fx, fy, cx, cy, dist, axis))
                out[r, c] = u_plane[r, c] + np.float32(u_decoded[r, c] - seen)
    return out


@nb.njit(cache=True, inline="always")
def _project(X, Y, Z, fx, fy, cx, cy, dist, axis):
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    z = 1.0 / Z if Z != 0.0 else 1.0
    x = X * z
    y = Y * z
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if axis == 0:
        return fx * (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)) + cx
    return fy * (y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y) + cy
