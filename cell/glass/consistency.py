"""Outlier rejection of the multi-camera glass points by the consistency of their cameras (3.4).

At a true surface point every camera that sees it measures the same normal up to noise. Model: each
camera's normal carries independent isotropic tangent noise of sigma (rad) per axis. The feedback moves the
point along the primary ray (one parameter) to minimise the sum S of squared angles of the c normals to their
mean, so S / sigma^2 follows chi-square with 2(c - 1) - 1 degrees of freedom. Hence:

1. sigma is estimated from the data, robustly: the median over points of S / median(chi2(dof)) (the
   outliers move a median little), so no angle threshold is hard-coded;
2. a point fails when its S is improbable at level ``alpha`` (chi-square upper tail);
3. the depth is pinned only as sharply as S curves along the ray: least squares gives the variance of the
   ray parameter as 2 sigma^2 / S''; along the normal it is scaled by |cos i|. A point whose depth standard
   error exceeds ``max_depth_sigma_mm`` is rejected (e.g. two cameras looking from nearly the same side);
4. a point seen by one camera only is unconfirmed: its depth rests on the CAD normal (2.3), so it is kept
   apart, not judged by this test -- unless it was measured by multi-projection (2.4), which assumes no
   normal: such a point is judged by its own two-screen geometry (:func:`check_projection`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2


@dataclass(frozen=True)
class Consistency:
    """Per point: accepted, the chi-square tail probability of its residual and its depth standard error
    along the normal (mm; inf when unconfirmed); ``sigma_rad``: the estimated per-camera normal noise."""

    accepted: NDArray[np.bool_]
    p_value: NDArray[np.float64]
    depth_sigma_mm: NDArray[np.float64]
    sigma_rad: float


def residual_dof(n_cameras: NDArray[np.int64]) -> NDArray[np.int64]:
    """Degrees of freedom of the feedback residual: 2 per extra camera, less the one fitted depth."""
    return np.maximum(2 * (np.asarray(n_cameras) - 1) - 1, 0)


def normal_noise(residual: NDArray[np.float64], n_cameras: NDArray[np.int64]) -> float:
    """Robust estimate of the per-camera normal noise sigma (rad) from the residuals of confirmed points."""
    dof = residual_dof(n_cameras)
    ok = dof > 0
    if not np.any(ok):
        return float("nan")
    return float(np.sqrt(np.median(residual[ok] / chi2.ppf(0.5, dof[ok]))))


def check_consistency(
    residual: NDArray[np.float64],
    curvature: NDArray[np.float64],
    n_cameras: NDArray[np.int64],
    cos_incidence: NDArray[np.float64],
    alpha: float,
    max_depth_sigma_mm: float,
) -> Consistency:
    """Judge every point (see the module docstring); ``cos_incidence`` = |ray . normal| per point."""
    sigma = normal_noise(residual, n_cameras)
    dof = residual_dof(n_cameras)
    confirmed = dof > 0
    p = np.zeros(len(residual))
    depth_sigma = np.full(len(residual), np.inf)
    if confirmed.any():
        p[confirmed] = chi2.sf(residual[confirmed] / sigma**2, dof[confirmed])
        curv = curvature[confirmed]
        with np.errstate(divide="ignore", invalid="ignore"):
            var_t = np.where(curv > 0, 2 * sigma**2 / curv, np.inf)
        depth_sigma[confirmed] = np.sqrt(var_t) * np.abs(cos_incidence[confirmed])
    accepted = confirmed & (p > alpha) & (depth_sigma <= max_depth_sigma_mm)
    return Consistency(accepted, p, depth_sigma, sigma)


def check_projection(
    miss_mm: NDArray[np.float64],
    lever: NDArray[np.float64],
    sin_angle: NDArray[np.float64],
    cos_incidence: NDArray[np.float64],
    alpha: float,
    max_depth_sigma_mm: float,
) -> Consistency:
    """Judge multi-projection points by their own geometry (cell.glass.multiprojection.ProjectionFit).

    Model: the second screen point W2 carries isotropic noise of sigma_w (mm per axis). Its component out of
    the plane of ray and W1-W2 line shows as the miss distance, miss = lever * e_out; its component in that
    plane moves the point along the ray by lever * e_in / sin_angle. So (miss / lever)^2 / sigma_w^2 follows
    chi-square with 1 degree of freedom: sigma_w is estimated robustly from all points (median), a point fails
    when its miss is improbable at ``alpha`` or when its depth standard error along the normal,
    lever * sigma_w / sin_angle * |cos i|, exceeds ``max_depth_sigma_mm``. NaN inputs (no second-screen
    fit) are not accepted. ``sigma_rad`` of the result holds sigma_w (mm)."""
    e_out = miss_mm / lever
    fitted = np.isfinite(e_out) & (sin_angle > 0)
    p = np.zeros(len(miss_mm))
    depth_sigma = np.full(len(miss_mm), np.inf)
    if not fitted.any():
        return Consistency(fitted, p, depth_sigma, float("nan"))
    sigma_w = float(np.sqrt(np.median(e_out[fitted] ** 2) / chi2.ppf(0.5, 1)))
    if sigma_w > 0:
        p[fitted] = chi2.sf(e_out[fitted] ** 2 / sigma_w**2, 1)
    else:  # noise-free data: every exact fit passes
        p[fitted] = np.where(e_out[fitted] == 0, 1.0, 0.0)
    depth_sigma[fitted] = lever[fitted] * sigma_w / sin_angle[fitted] * np.abs(cos_incidence[fitted])
    accepted = fitted & (p > alpha) & (depth_sigma <= max_depth_sigma_mm)
    return Consistency(accepted, p, depth_sigma, sigma_w)
