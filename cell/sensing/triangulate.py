"""From decoded projector coordinates to an organised cloud (H, W, 3) in the sensor frame {C} (mm).

Two models behind one interface (:class:`Triangulator`):

* :class:`PinholeTriangulator` -- the standard model: the camera ray of each pixel (OpenCV intrinsics and
  distortion, cv2.undistortPoints) meets the plane of its decoded projector column (projector at ``T_C_P``;
  with its lens distortion, the decoded column is corrected at the point's own projector row, iterated).
* :class:`ReferencePlaneTriangulator` -- the dissertation's per-pixel model (2.1.1, 2.2): L is the distance on
  the reference plane between where the camera sees the pixel (C) and where the same code is seen on the
  reference plane in the same row (A), corrected by the offset angle (L' = L sec alpha, eq 2.9); then
  h = L'S/(d + L') with per-pixel d and S (eq 2.8), Z = S0 - h (S0 the reference plane's depth) and X, Y
  from the perspective model (eqs 2.2-2.3, written in the OpenCV optical frame: X = Z * x_n, Y = Z * y_n with
  undistorted normalised coordinates, which is eq 2.3's -(S-h)/F * u with the image axes un-mirrored). d, S
  come from stepping a plane (eq 2.7, :func:`fit_d_S`): :mod:`cell.calibration.sensor` measures them on the
  cell; :func:`reference_model_from_geometry` runs the same procedure on analytic planes of the configured
  geometry (the simulated scan without a sensor calibration).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Protocol, runtime_checkable

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.config import SensorConfig
from cell.sensing import _cloud_kernel
from cell.sensing.decode import AxisDecode, Decoded

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-15)


@dataclass
class SensorCloud:
    """An organised cloud in {C} (mm, NaN where invalid) with the per-pixel reasons and quality."""

    points_C: NDArray[np.float32]  # (H, W, 3)
    reasons: NDArray[np.uint8]  # Reason bits (decode.Reason); 0 = valid point
    contrast: NDArray[np.float32]  # (white - black) / (white + black)
    sharpness: NDArray[np.float32]  # edge swing / modulation (GCLS) or phase modulation ratio (GCPS)

    @property
    def valid(self) -> NDArray[np.bool_]:
        return self.reasons == 0


@runtime_checkable
class Triangulator(Protocol):
    """Turns a decoded stack into an organised cloud in the sensor frame."""

    def triangulate(self, decoded: Decoded) -> SensorCloud: ...


def normalized_coords(
    K: NDArray[np.float64], dist: NDArray[np.float64], width: int, height: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Undistorted normalised image coordinates (x_n, y_n), each (H, W), of every pixel centre."""
    return _normalized(tuple(K.ravel()), tuple(np.asarray(dist, dtype=np.float64).ravel()), width, height)


@lru_cache(maxsize=4)
def _normalized(K: tuple, dist: tuple, width: int, height: int) -> tuple[NDArray, NDArray]:
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(
        pts, np.array(K).reshape(3, 3), np.array(dist), None, None, None, _UNDISTORT_CRITERIA
    ).reshape(height, width, 2)
    xn, yn = xy[..., 0].copy(), xy[..., 1].copy()
    xn.setflags(write=False)
    yn.setflags(write=False)
    return xn, yn


def _cloud(decoded: Decoded, ad: AxisDecode, X: NDArray, Y: NDArray, Z: NDArray) -> SensorCloud:
    reasons = ad.reasons.copy()
    bad = ~np.isfinite(Z) | (Z <= 0)
    reasons[bad & (reasons == 0)] = np.uint8(8)  # geometrically impossible: treat as inconsistent
    pts = np.stack([X, Y, Z], axis=-1).astype(np.float32)
    pts[reasons != 0] = np.nan
    return SensorCloud(pts, reasons, decoded.contrast, ad.sharpness)


class PinholeTriangulator:
    """Camera ray / projector column-plane (or row-plane) intersection; OpenCV conventions, mm."""

    def __init__(
        self,
        K_cam: NDArray,
        dist_cam: NDArray,
        size: tuple[int, int],
        K_proj: NDArray,
        T_C_P: NDArray,
        dist_proj: NDArray | None = None,
    ):
        self.K_proj = np.asarray(K_proj, dtype=np.float64)
        self.T_C_P = np.asarray(T_C_P, dtype=np.float64)
        self.dist_proj = np.zeros(5) if dist_proj is None else np.asarray(dist_proj, dtype=np.float64)
        self.xn, self.yn = normalized_coords(np.asarray(K_cam, float), np.asarray(dist_cam, float), *size)
        R, t = self.T_C_P[:3, :3], self.T_C_P[:3, 3]
        # Column plane of projector coordinate u: n_P = e_x - a e_z, a = (u - cx)/fx, through the projector
        # centre. In {C}: n_C = R[:,0] - a R[:,2]; a ray X = z (x_n, y_n, 1) meets it at
        # z = (R0.t - a R2.t) / (R0.r - a R2.r). Precompute the per-pixel dot products (rows: R[:,1]).
        self._t_dot = {i: float(R[:, i] @ t) for i in range(3)}
        self._r_dot = {i: R[0, i] * self.xn + R[1, i] * self.yn + R[2, i] for i in range(3)}

    @classmethod
    def from_sensor(cls, sensor: SensorConfig) -> PinholeTriangulator:
        cam, proj = sensor.camera, sensor.projector
        return cls(
            cam.K(),
            cam.distortion.as_array(),
            (cam.width_px, cam.height_px),
            proj.K(),
            proj.T_C_P.matrix(),
            proj.distortion.as_array(),
        )

    def depth(self, u: NDArray, axis: str = "columns") -> NDArray[np.float64]:
        """Z (mm) in {C} of every pixel given its projector coordinate ``u`` along ``axis``."""
        k = 0 if axis == "columns" else 1
        f, c = self.K_proj[k, k], self.K_proj[k, 2]
        a = (u.astype(np.float64) - c) / f
        with np.errstate(invalid="ignore", divide="ignore"):
            return (self._t_dot[k] - a * self._t_dot[2]) / (self._r_dot[k] - a * self._r_dot[2])

    def triangulate(self, decoded: Decoded, iterations: int = 3) -> SensorCloud:
        """One fused compiled pass (:func:`_cloud_kernel.pinhole_cloud`); same arithmetic as :meth:`depth`.
        A projector lens with distortion bends its column planes: the decoded column ``u`` is where the lens
        put the stripe, so each point is projected back through the lens (cv2.projectPoints' model,
        :func:`_cloud_kernel.project_axis`) and the column the pinhole plane uses is moved by what the lens
        added, ``iterations`` times (Newton with the lens's derivative taken as 1: the distortion is a few
        pixels, the step converges to well under 0.01 px)."""
        ad = decoded.primary()
        k = 0 if ad.axis == "columns" else 1
        u_plane = ad.u
        pts, reasons = self._pinhole(u_plane, ad.reasons, k)
        if np.any(self.dist_proj):
            T_P_C = np.linalg.inv(self.T_C_P)
            K = self.K_proj
            lens = (
                T_P_C[:3, :3].copy(),
                T_P_C[:3, 3].copy(),
                K[0, 0],
                K[1, 1],
                K[0, 2],
                K[1, 2],
                self.dist_proj,
            )
            u_decoded = np.asarray(ad.u, dtype=np.float32)
            u_plane = u_decoded
            for _ in range(iterations):
                u_plane = _cloud_kernel.lens_step(pts, reasons, u_plane, u_decoded, *lens, k)
                pts, reasons = self._pinhole(u_plane, ad.reasons, k)
        return SensorCloud(pts, reasons, decoded.contrast, ad.sharpness)

    def _pinhole(self, u: NDArray, reasons: NDArray, k: int) -> tuple[NDArray, NDArray]:
        R = self.T_C_P[:3, :3]
        return _cloud_kernel.pinhole_cloud(
            u,
            reasons,
            self.xn,
            self.yn,
            float(self.K_proj[k, k]),
            float(self.K_proj[k, 2]),
            np.ascontiguousarray(R[:, k]),
            np.ascontiguousarray(R[:, 2]),
            self._t_dot[k],
            self._t_dot[2],
        )


def fit_d_S(h_steps: NDArray, L_steps: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-pixel baseline d and stand-off S (mm) by linear least squares, eq 2.7:
    [h_k, -L_k] [d, S]^T = -h_k L_k.

    ``h_steps`` (n,) or (n, ...) plane heights above the reference plane, ``L_steps`` (n, ...) the measured L;
    NaN samples are left out per pixel. Closed-form 2x2 normal equations, vectorised over pixels.
    """
    L = np.asarray(L_steps, dtype=np.float64)
    h = np.broadcast_to(np.asarray(h_steps, dtype=np.float64).reshape((-1,) + (1,) * (L.ndim - 1)), L.shape)
    ok = np.isfinite(L) & np.isfinite(h)
    h0, L0 = np.where(ok, h, 0.0), np.where(ok, L, 0.0)
    a11, a12, a22 = (h0 * h0).sum(0), -(h0 * L0).sum(0), (L0 * L0).sum(0)
    b1, b2 = (-h0 * h0 * L0).sum(0), (h0 * L0 * L0).sum(0)
    det = a11 * a22 - a12 * a12
    with np.errstate(invalid="ignore", divide="ignore"):
        d = (a22 * b1 - a12 * b2) / det
        S = (a11 * b2 - a12 * b1) / det
    few = ok.sum(0) < 2
    return np.where(few, np.nan, d), np.where(few, np.nan, S)


@dataclass
class ReferencePlaneTriangulator:
    """The dissertation's per-pixel model. Maps are (H, W); the reference table maps, per camera row, a
    projector coordinate to the normalised x where the reference plane shows it."""

    d: NDArray[np.float64]  # per-pixel baseline (mm)
    S: NDArray[np.float64]  # per-pixel stand-off (mm)
    alpha: NDArray[np.float64]  # per-pixel offset angle (rad), eq 2.9
    xn: NDArray[np.float64]
    yn: NDArray[np.float64]
    ref_x: NDArray[np.float64]  # (H, K) normalised x on the reference plane of code u0 + k*du, per row
    u0: float
    du: float
    res_mm: float  # mm on the reference plane per unit of normalised x (the reference plane's depth)
    sign: float = 1.0  # +1 when the projector sits on the camera's +x side

    def length(self, u: NDArray) -> NDArray[np.float64]:
        """L (mm, eq 2.6) of every pixel: C is the pixel, A where the reference plane shows code ``u``."""
        f = (u.astype(np.float64) - self.u0) / self.du
        K = self.ref_x.shape[1]
        inside = (f >= 0) & (f <= K - 1)
        i = np.clip(np.floor(np.nan_to_num(f)), 0, K - 2).astype(np.intp)
        w = np.nan_to_num(f) - i
        rows = np.arange(self.ref_x.shape[0])[:, None]
        xa = self.ref_x[rows, i] * (1 - w) + self.ref_x[rows, i + 1] * w
        return np.where(inside, self.sign * (self.xn - xa) * self.res_mm, np.nan)

    def triangulate(self, decoded: Decoded) -> SensorCloud:
        ad = decoded.primary()
        L = self.length(ad.u) / np.cos(self.alpha)  # eq 2.9
        h = L * self.S / (self.d + L)  # eq 2.8
        # Eq 2.3 writes Z = S - h. The fitted S(i, j) is poorly determined on its own (eq 2.7's d and S are
        # ~0.996 correlated: 10 um of L noise moves S by ~0.4 mm while h moves by ~3 um, docs/sensing.md), so
        # the depth is taken from the reference plane itself (depth res_mm, perpendicular to the optical
        # axis): Z = S0 - h.
        Z = self.res_mm - h
        return _cloud(decoded, ad, Z * self.xn, Z * self.yn, Z)


def reference_table(u_ref: NDArray, xn: NDArray, du: float = 0.25) -> tuple[NDArray, float]:
    """Invert a reference-plane code map ``u_ref`` (H, W; NaN where unknown) along each row: returns the table
    (H, K) of normalised x at codes u0 + k*du and u0. Rows must be monotone in u (they are, on a plane)."""
    H, W = u_ref.shape
    u0 = float(np.floor(np.nanmin(u_ref)))
    K = int(np.ceil((np.nanmax(u_ref) - u0) / du)) + 2
    grid = u0 + du * np.arange(K)
    flip = np.nanmedian(np.diff(u_ref, axis=1)) < 0
    uu, xx = (u_ref[:, ::-1], xn[:, ::-1]) if flip else (u_ref, xn)
    # All rows at once: offset each row's codes by a multiple of a span larger than any code, then one
    # np.interp over the concatenation (rows never mix because the offsets separate them).
    span = (np.nanmax(u_ref) - u0) + 10 * du + 1.0
    off = np.arange(H)[:, None] * span
    ok = np.isfinite(uu)
    table = np.interp((grid[None, :] + off).ravel(), (uu + off)[ok], xx[ok]).reshape(H, K)
    lo = np.where(ok.any(1), np.nanmin(np.where(ok, uu, np.inf), 1), np.inf)[:, None]
    hi = np.where(ok.any(1), np.nanmax(np.where(ok, uu, -np.inf), 1), -np.inf)[:, None]
    table[(grid[None, :] < lo) | (grid[None, :] > hi)] = np.nan
    return table, u0


def offset_angle(
    code_ref: Callable[[NDArray, NDArray], NDArray], xn: NDArray, yn: NDArray, baseline_C: NDArray
) -> NDArray[np.float64]:
    """Per-pixel offset angle alpha (rad, eq 2.9) of the row look-up: with g the reference plane's code
    gradient (stripe normal) at the pixel, x the row direction and b the baseline direction on the reference
    plane, cos(alpha) = (b.g) / (x.g), so that L' = L sec(alpha) for the row distance L. When the stripes run
    along the camera columns (g = x) this is the dissertation's angle between the baseline and the stripe
    normal (Fig 2.10); the calibration (cell.calibration.sensor) stores the same quantity. Exact for straight
    parallel stripes; a tilted projector's stripes fan out (keystone), so the stripe met at A, L away, is
    turned slightly from the one at the pixel (about 0.03 mm of height at 10 deg and h = 30 mm on the small
    test sensor, tests/test_sensing_alpha.py). ``code_ref(x, y)`` gives the reference-plane code at normalised
    camera coordinates; ``baseline_C`` is the projector centre's (x, y) in {C} (mm), the direction along which
    a raised point's code moves on the reference plane."""
    eps = 1e-4  # normalised units (~0.04 camera px on the prototype): central differences of a smooth map
    gx = code_ref(xn + eps, yn) - code_ref(xn - eps, yn)
    gy = code_ref(xn, yn + eps) - code_ref(xn, yn - eps)
    b = np.asarray(baseline_C, dtype=np.float64) / np.linalg.norm(baseline_C)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.arccos(np.clip((b[0] * gx + b[1] * gy) / gx, -1.0, 1.0))


def reference_model_from_geometry(
    sensor: SensorConfig, heights_mm: tuple[float, ...] = (-40, -20, 20, 40, 60)
) -> ReferencePlaneTriangulator:
    """Per-pixel (d, S, alpha) from the known sensor geometry, by the calibration procedure of 2.2 run on
    analytic planes: reference plane Z = standoff, planes stepped by ``heights_mm`` toward the camera, L' of
    every pixel and step the displacement of its code along the baseline on the reference plane (what the
    calibration measures with encoded points), then eq 2.7 (:func:`fit_d_S`). The reference table (codes of
    the reference plane along each camera row) is what :meth:`ReferencePlaneTriangulator.length` looks up.
    alpha per pixel from :func:`offset_angle` (zero when the baseline runs along the camera rows, as on the
    prototype)."""
    cam, proj = sensor.camera, sensor.projector
    W, H = cam.width_px, cam.height_px
    xn, yn = normalized_coords(cam.K(), cam.distortion.as_array(), W, H)
    T_P_C = np.linalg.inv(proj.T_C_P.matrix())
    S0 = sensor.standoff_mm

    def code(z: float, x: NDArray = xn, y: NDArray = yn) -> NDArray:
        P = np.stack([x * z, y * z, np.full_like(x, z)], -1) @ T_P_C[:3, :3].T + T_P_C[:3, 3]
        return proj.fx_px * P[..., 0] / P[..., 2] + proj.cx_px

    t = proj.T_C_P.matrix()[:3, 3]
    # The reference plane is known analytically here, so its code table can extend beyond the camera's field
    # (a raised point's A lies outside the field near the image border): virtual rows span 2.2x the field.
    span = xn.max() - xn.min()
    x_ext = np.broadcast_to(np.linspace(xn.min() - 0.6 * span, xn.max() + 0.6 * span, 4 * W), (H, 4 * W))
    y_ext = np.broadcast_to(yn.mean(axis=1, keepdims=True), (H, 4 * W))
    table, u0 = reference_table(code(S0, x_ext, y_ext), x_ext)
    alpha = offset_angle(lambda x, y: code(S0, x, y), xn, yn, t[:2])
    model = ReferencePlaneTriangulator(
        np.ones((H, W)), np.ones((H, W)), alpha, xn, yn, table, u0, 0.25, S0, float(np.sign(t[0]) or 1.0)
    )
    # L' per step as the calibration measures it (cell.calibration.sensor, steps 5-6): how far the pixel's
    # code moves on the reference plane, along the baseline, when the plane rises by h. Here it is exact:
    # A' is where the projector ray through the raised point D meets the reference plane, C' is the pixel's.
    b = t[:2] / np.linalg.norm(t[:2])
    C_ref = np.stack([xn, yn], -1) * S0
    L = []
    for h in heights_mm:
        D = np.stack([xn, yn, np.ones_like(xn)], -1) * (S0 - h)
        A = t + (D - t) * ((S0 - t[2]) / (D[..., 2:] - t[2]))
        L.append((C_ref - A[..., :2]) @ b)
    model.d, model.S = fit_d_S(np.asarray(heights_mm, dtype=np.float64), np.stack(L))
    return model
