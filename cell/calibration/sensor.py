"""Per-pixel (pixel-to-pixel) calibration of the structured-light sensor, dissertation 2.2 and 5.1.1.

The flat reference board is stepped n times toward the sensor by known heights h_k (h_0 = 0 is the reference
plane). At every step both stripe directions are decoded (step 1) and the encoded points P_k(h_i, v_j), the
intersections of horizontal and vertical code lines, are found with sub-pixel precision (steps 2-4,
:mod:`cell.calibration.codepoints`). Per encoded point:

* the vectors P_0 P_k on the reference plane (mm: undistorted normalised camera coordinates times the
  reference depth, i.e. eq 2.6 with res = S0 / f) give the offset angle alpha to the stripe gradient
  (step 5; the average of the alpha_k weighted by vector length, because short vectors have noisy angles);
* L'_k = |P_0 P_k| along their common direction and h_k give d and S by linear least squares (eq 2.7, step 6).

The per-point d, S and alpha are interpolated to every camera pixel (linear on the Delaunay triangulation of
the points, nearest outside) and, with the reference plane's column code map, make the
:class:`cell.sensing.triangulate.ReferencePlaneTriangulator` that measures with L' = L sec(alpha) (eq 2.9).
alpha is stored as the angle that triangulator needs: with the stripe gradient g, the row direction x and the
correspondence direction b, cos(alpha) = (b.g)/(x.g), which is the dissertation's angle between b and g when
the stripes run across the rows (as they do for column stripes).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

from cell.calibration.codepoints import locate_codes
from cell.calibration.rejection import fit_residuals, robust_fit, spatial_outliers
from cell.calibration.store import load_calibration, save_calibration, save_map_png
from cell.config import CameraConfig, ProjectorConfig
from cell.errors import CalibrationError, ConfigError
from cell.geometry import Pose
from cell.sensing.decode import Decoded
from cell.sensing.triangulate import ReferencePlaneTriangulator, normalized_coords, reference_table

MIN_STEPS = 4  # the reference plane + 3 steps: eq 2.7 has 2 unknowns, and 1 degree of freedom judges the fit


@dataclass
class SensorCalibration:
    """Result of the per-pixel calibration: the measuring model and what the technician needs to judge it."""

    model: ReferencePlaneTriangulator
    points_px: NDArray[np.float64]  # (N, 2) camera position of each encoded point (mean over the steps)
    d_mm: NDArray[np.float64]  # (N,) per encoded point
    S_mm: NDArray[np.float64]
    alpha_rad: NDArray[np.float64]
    residual_mm: NDArray[np.float64]  # (N,) RMS of h_k - L'_k S/(d + L'_k) over the steps
    heights_mm: NDArray[np.float64]
    height_sigma_mm: float  # median predicted height standard error at eval_height_mm (the quality figure)
    figures: dict[str, Any] = field(default_factory=dict)


def code_grid(u_ref: NDArray, v_ref: NDArray, n_points: int, margin: float = 0.03) -> NDArray[np.float64]:
    """A square grid of about ``n_points`` projector codes (u, v) spanning the codes seen on the reference
    plane (inside the 3rd-97th percentile, so every point has neighbours in the image)."""
    n = int(round(np.sqrt(n_points)))
    ok = np.isfinite(u_ref) & np.isfinite(v_ref)
    if ok.sum() < 100:
        raise CalibrationError(
            "reference step: fewer than 100 pixels decoded in both directions; is the board "
            "in view, lit by the projector and inside the depth of field?"
        )
    ulo, uhi = np.percentile(u_ref[ok], [100 * margin, 100 * (1 - margin)])
    vlo, vhi = np.percentile(v_ref[ok], [100 * margin, 100 * (1 - margin)])
    uu, vv = np.meshgrid(np.linspace(ulo, uhi, n), np.linspace(vlo, vhi, n))
    return np.column_stack([uu.ravel(), vv.ravel()])


class SensorCalibrator:
    """Feed the decoded steps in order with :meth:`add_step`, then :meth:`finish`. Keeps only the encoded
    points of each step (not the images), so 30 full-resolution steps fit in memory."""

    def __init__(
        self,
        camera: CameraConfig,
        projector: ProjectorConfig,
        reference_depth_mm: float,
        n_points: int = 65536,
        K: NDArray | None = None,
        dist: NDArray | None = None,
        reject_k: float = 5.0,
        eval_height_mm: float = 30.0,
    ):
        self.camera, self.projector = camera, projector
        self.S0 = float(reference_depth_mm)
        self.n_points = n_points
        self.reject_k = reject_k  # robust sigmas beyond which samples and points are rejected (rejection.py)
        self.eval_height_mm = eval_height_mm  # where the quality figure is judged (predicted_height_sigma)
        self.K = camera.K() if K is None else np.asarray(K, float)
        self.dist = camera.distortion.as_array() if dist is None else np.asarray(dist, float)
        self.heights: list[float] = []
        self.positions: list[NDArray] = []  # (N, 2) px per step
        self.codes: NDArray | None = None
        self.u_ref: NDArray | None = None
        self.grad: NDArray | None = None

    def add_step(self, height_mm: float, decoded: Decoded) -> int:
        """Add one step (board ``height_mm`` above the reference plane; the first step is the reference, 0).
        Returns how many encoded points were found."""
        W, H = self.camera.width_px, self.camera.height_px
        if set(decoded.axes) != {"columns", "rows"}:
            raise CalibrationError(
                "sensor calibration needs both stripe directions decoded (direction 'both')"
            )
        u, v = decoded.axes["columns"].u, decoded.axes["rows"].u
        if u.shape != (H, W):
            raise CalibrationError(
                f"step {len(self.heights)}: decoded maps are {u.shape[1]}x{u.shape[0]}, the "
                f"camera '{self.camera.name}' is {W}x{H}: resolution mismatch"
            )
        if not self.heights:
            if height_mm != 0:
                raise CalibrationError(
                    f"the first step is the reference plane and must have height 0, got {height_mm} mm"
                )
            self.codes = code_grid(u, v, self.n_points)
            self.u_ref = u.astype(np.float64)
        elif not height_mm > self.heights[-1]:
            raise CalibrationError(
                f"step {len(self.heights)}: height {height_mm} mm is not above the previous "
                f"{self.heights[-1]} mm; steps must increase toward the sensor"
            )
        codes = self.codes
        assert codes is not None  # set by the reference step
        pos, grad = locate_codes(u, v, codes, (self.projector.width_px, self.projector.height_px))
        if self.grad is None:
            self.grad = grad
        found = int(np.isfinite(pos[:, 0]).sum())
        if found < 0.2 * len(codes):
            raise CalibrationError(
                f"step {len(self.heights)} at {height_mm} mm: only {found} of "
                f"{len(codes)} encoded points found; is the board in view?"
            )
        self.heights.append(float(height_mm))
        self.positions.append(pos)
        return found

    def _plane_mm(self, px: NDArray) -> NDArray:
        """Camera pixels (N, 2) to reference-plane coordinates (mm): undistorted normalised x S0."""
        out = np.full_like(px, np.nan)
        ok = np.isfinite(px[:, 0])
        if ok.any():
            out[ok] = (
                cv2.undistortPoints(px[ok].reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2) * self.S0
            )
        return out

    def finish(self, stride: int = 1) -> SensorCalibration:
        """Fit d, S, alpha per encoded point (eq 2.7, steps 5-6), interpolate to every pixel, build the model.

        ``stride`` > 1 uses every stride-th code line in each direction (1/stride^2 of the points): Table 5.1
        compares 4096, 16384 and 65536 points from one set of images this way."""
        n = len(self.heights)
        if n < MIN_STEPS:
            raise CalibrationError(
                f"sensor calibration: the reference plane and {n - 1} steps; at least {MIN_STEPS - 1} steps "
                "are needed (30 recommended)"
            )
        assert self.codes is not None and self.grad is not None and self.u_ref is not None  # the first step
        h = np.asarray(self.heights)
        side = int(round(np.sqrt(len(self.codes))))
        sel: NDArray[np.bool_] = np.zeros((side, side), bool)
        sel[::stride, ::stride] = True
        sel = sel.ravel()
        m = np.stack([self._plane_mm(p[sel]) for p in self.positions])  # (n, N, 2)
        b = m[1:] - m[0]  # P0Pk vectors (n-1, N, 2)
        total = np.nansum(b, axis=0)
        bhat = total / np.maximum(np.linalg.norm(total, axis=1, keepdims=True), 1e-12)
        L = np.concatenate([np.zeros((1, len(bhat))), np.einsum("knj,nj->kn", b, bhat)])
        L[np.isnan(m[:, :, 0])] = np.nan
        d, S, L, rejected = robust_fit(h, L, self.reject_k)
        sub = len(range(0, side, stride))
        with np.errstate(invalid="ignore", divide="ignore"):
            spatial = spatial_outliers(d / S, sub, self.reject_k)
        d[spatial], S[spatial] = np.nan, np.nan
        rejected["spatial_outliers"] = int(spatial.sum())
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # points seen in no step: NaN, filtered below
            res = np.sqrt(np.nanmean(fit_residuals(h, L, d, S) ** 2, axis=0))
            grad = self.grad[sel]
            g = grad * np.sign(np.sum(grad * bhat, axis=1, keepdims=True))
            alpha_diss = np.arctan2(g[:, 0] * bhat[:, 1] - g[:, 1] * bhat[:, 0], np.sum(g * bhat, axis=1))
            cos_eff = np.clip(np.sum(bhat * g, axis=1) / np.abs(g[:, 0]), -1, 1)
        alpha_eff = np.arccos(cos_eff)
        ok = (
            np.isfinite(d)
            & np.isfinite(S)
            & np.isfinite(alpha_eff)
            & (np.sum(np.isfinite(L), 0) >= MIN_STEPS)
        )
        sigma_h = predicted_height_sigma(h, L, np.where(ok, d, np.nan), S, self.eval_height_mm)
        if ok.sum() < 16:
            raise CalibrationError(f"sensor calibration: only {int(ok.sum())} encoded points could be fitted")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # codes never seen: NaN, left out
            pos = np.nanmean(np.stack(self.positions), axis=0)[sel]
        ok &= np.isfinite(pos[:, 0])
        W, H = self.camera.width_px, self.camera.height_px
        yy, xx = np.mgrid[0:H, 0:W]
        grid = np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64)
        vals = np.column_stack([d[ok], S[ok], alpha_eff[ok]])
        lin = LinearNDInterpolator(pos[ok], vals)(grid)
        near = NearestNDInterpolator(pos[ok], vals)(grid[np.isnan(lin[:, 0])])
        lin[np.isnan(lin[:, 0])] = near
        maps = lin.reshape(H, W, 3)
        xn, yn = normalized_coords(self.K, self.dist, W, H)
        table, u0 = reference_table(self.u_ref, xn)
        sign = float(np.sign(np.nanmean(bhat[:, 0])) or 1.0)
        model = ReferencePlaneTriangulator(
            maps[..., 0], maps[..., 1], maps[..., 2], xn, yn, table, u0, 0.25, self.S0, sign
        )
        figures = {
            "steps": n,
            "heights_mm": [float(x) for x in h],
            "encoded_points": int(sel.sum()),
            "fitted_points": int(ok.sum()),
            "d_mm": _stats(d[ok]),
            "S_mm": _stats(S[ok]),
            "alpha_deg": _stats(np.degrees(alpha_diss[ok])),
            "residual_mm": _stats(res[ok]),
            "height_sigma_mm": {"at_height_mm": self.eval_height_mm, **_stats(sigma_h[ok])},
            "rejected": rejected,
        }
        quality = float(np.nanmedian(sigma_h[ok]))
        return SensorCalibration(model, pos, d, S, alpha_eff, res, h, quality, figures)


def _stats(x: NDArray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    return {
        "mean": float(x.mean()),
        "std": float(x.std()),
        "min": float(x.min()),
        "max": float(x.max()),
        "rms": float(np.sqrt(np.mean(x * x))),
    }


def predicted_height_sigma(h: NDArray, L: NDArray, d: NDArray, S: NDArray, eval_height_mm: float) -> NDArray:
    """Per point (N,): standard error (mm) of the height the fitted model h = L S/(d + L) gives at
    ``eval_height_mm`` above the reference plane, propagated from the covariance of the eq 2.7 fit.

    Eq 2.7 is linear least squares [h_k, -L_k][d, S]^T = -h_k L_k, so Cov(d, S) = s^2 (A^T A)^-1 with the
    row residual variance s^2 pooled over all points (sum of squared residuals / sum of degrees of freedom;
    a point of 3 steps has 1). The height's gradient at L_e = h_e d/(S - h_e) is (-L_e S, L_e (d + L_e)) /
    (d + L_e)^2. This is the figure by which calibrations are ranked: a short or narrow run fits its own
    steps closely but extrapolates poorly, and this says so, where residual / sqrt(steps - 2) did not.
    ``h`` (n,) step heights, ``L`` (n, N) mm (NaN where not seen), ``d``, ``S`` (N,) (NaN: not fitted)."""
    ok = np.isfinite(L) & np.isfinite(d) & np.isfinite(S)
    hk = np.where(ok, h[:, None], 0.0)
    Lk = np.where(ok, L, 0.0)
    a11, a12, a22 = (hk * hk).sum(0), -(hk * Lk).sum(0), (Lk * Lk).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(ok, hk * (d + Lk) - Lk * S, 0.0)  # eq 2.7 row residuals
        informative = (ok & (h[:, None] != 0)).sum(0)  # the reference row (h = L = 0) holds no information
        fitted = np.isfinite(d) & np.isfinite(S) & (informative > 2)
        s2 = (r[:, fitted] ** 2).sum() / max(int((informative[fitted] - 2).sum()), 1)
        Le = eval_height_mm * d / (S - eval_height_mm)
        gd, gS = -Le * S / (d + Le) ** 2, Le / (d + Le)
        var = s2 * (gd * gd * a22 - 2 * gd * gS * a12 + gS * gS * a11) / (a11 * a22 - a12 * a12)
    return np.where(fitted, np.sqrt(var), np.nan)


def save_sensor_calibration(
    cal: SensorCalibration,
    path: Path,
    camera: CameraConfig,
    projector: ProjectorConfig,
    force: bool = False,
    reference_T_B_T: Pose | None = None,
    made_for: str | None = None,
) -> Path:
    """Versioned file of the per-pixel model (see :mod:`cell.calibration.store`); worse-than-existing files
    (by :attr:`SensorCalibration.height_sigma_mm`, :func:`predicted_height_sigma`) are refused unless
    ``force``. Writes d/S/alpha maps as PNG beside it. ``reference_T_B_T`` is the robot flange pose the
    reference plane was seen from: heights above that plane (the flat test) need the camera there again."""
    m = cal.model
    arrays = {
        "d": m.d,
        "S": m.S,
        "alpha": m.alpha,
        "ref_x": m.ref_x,
        "points_px": cal.points_px,
        "d_points": cal.d_mm,
        "S_points": cal.S_mm,
        "alpha_points": cal.alpha_rad,
        "residual_points": cal.residual_mm,
        "heights_mm": cal.heights_mm,
    }
    meta = {
        "camera": {
            "serial": camera.serial,
            "resolution": [camera.width_px, camera.height_px],
            "K": camera.K().tolist(),
            "dist": camera.distortion.as_array().tolist(),
        },
        "projector": {"serial": projector.serial, "resolution": [projector.width_px, projector.height_px]},
        "model": {"u0": m.u0, "du": m.du, "res_mm": m.res_mm, "sign": m.sign},
        "figures": cal.figures,
        "reference_T_B_T": None if reference_T_B_T is None else np.asarray(reference_T_B_T).tolist(),
        "quality": {
            "median_residual_mm": float(np.nanmedian(cal.residual_mm)),
            "height_sigma_mm": cal.height_sigma_mm,
            "height_sigma_at_mm": cal.figures.get("height_sigma_mm", {}).get("at_height_mm"),
        },
    }
    out = save_calibration(
        path, "sensor_per_pixel", arrays, meta, "quality.height_sigma_mm", force, made_for=made_for
    )
    stem = Path(path).with_suffix("")
    for name, arr in (("d", m.d), ("S", m.S), ("alpha", m.alpha)):
        save_map_png(stem.parent / f"{stem.name}_{name}.png", arr)
    return out


def load_sensor_model(path: Path, camera: CameraConfig) -> ReferencePlaneTriangulator:
    """The per-pixel model saved by :func:`save_sensor_calibration`; ConfigError if it was made for another
    camera resolution."""
    meta, a = load_calibration(path, "sensor_per_pixel")
    if list(meta["camera"]["resolution"]) != [camera.width_px, camera.height_px]:
        raise ConfigError(
            f"calibration is for a {meta['camera']['resolution']} camera, '{camera.name}' is "
            f"{camera.width_px}x{camera.height_px}: resolution mismatch",
            path=str(path),
        )
    K, dist = np.array(meta["camera"]["K"]), np.array(meta["camera"]["dist"])
    xn, yn = normalized_coords(K, dist, camera.width_px, camera.height_px)
    mm = meta["model"]
    return ReferencePlaneTriangulator(
        a["d"], a["S"], a["alpha"], xn, yn, a["ref_x"], mm["u0"], mm["du"], mm["res_mm"], mm["sign"]
    )
