"""Validation of a sensor calibration (dissertation 5.1): the flat test at a known height (Table 5.1), the
gauge
slot test (Fig 5.4: which slot depths are resolved) and plane / sphere fits of measured clouds."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.optimize import least_squares

from cell.errors import CalibrationError
from cell.sensing.triangulate import SensorCloud


def heights_from_cloud(cloud: SensorCloud, reference_depth_mm: float) -> NDArray[np.float64]:
    """Height above the reference plane (mm) of every valid pixel, for a reference plane perpendicular to the
    optical axis at ``reference_depth_mm``: h = S0 - Z."""
    return np.where(cloud.valid, reference_depth_mm - cloud.points_C[..., 2], np.nan)


def flat_test(
    cloud: SensorCloud, reference_depth_mm: float, true_height_mm: float, border_px: int = 8
) -> dict[str, Any]:
    """Error of a flat board measured at a known height: mean and standard deviation (mm), as Table 5.1."""
    h = heights_from_cloud(cloud, reference_depth_mm)[border_px:-border_px, border_px:-border_px]
    e = h[np.isfinite(h)] - true_height_mm
    if len(e) < 100:
        raise CalibrationError(f"flat test: only {len(e)} valid points; is the board in view?")
    return {
        "true_height_mm": true_height_mm,
        "points": int(len(e)),
        "mean_mm": float(e.mean()),
        "std_mm": float(e.std(ddof=1)),
        "p99_abs_mm": float(np.percentile(np.abs(e), 99)),
    }


def slot_test(
    points_P: NDArray,
    slots: list[dict[str, Any]],
    margin_mm: float = 1.0,
    band_mm: float = 6.0,
    alpha: float = 0.001,
) -> list[dict[str, Any]]:
    """Per gauge slot (``gauge.truth.json`` entries, part frame mm): measured depth = z of the bands beside
    the
    slot minus z inside it, as robust statistics (difference of medians, and of 10 % trimmed means, so that a
    few stray points cannot fake or hide a slot), and whether it is resolved: the surround is significantly
    higher than the slot floor by a rank test (Mann-Whitney U, one-sided, p < ``alpha``; no normality
    assumed) and the median depth is within half the nominal of it."""
    p = np.asarray(points_P, dtype=np.float64)
    out = []
    for s in slots:
        (x0, x1), (y0, y1) = s["x_range_mm"], s["y_range_mm"]
        iny = (p[:, 1] > y0 + margin_mm) & (p[:, 1] < y1 - margin_mm)
        inside = iny & (p[:, 0] > x0 + margin_mm) & (p[:, 0] < x1 - margin_mm)
        beside = iny & (
            ((p[:, 0] > x0 - margin_mm - band_mm) & (p[:, 0] < x0 - margin_mm))
            | ((p[:, 0] > x1 + margin_mm) & (p[:, 0] < x1 + margin_mm + band_mm))
        )
        zi, zb = p[inside, 2], p[beside, 2]
        if len(zi) < 10 or len(zb) < 10:
            raise CalibrationError(
                f"slot test: slot {s['index']} has {len(zi)} points inside and {len(zb)} "
                "beside it; is the gauge in view?"
            )
        depth_um = 1000 * (np.median(zb) - np.median(zi))
        trimmed_um = 1000 * (stats.trim_mean(zb, 0.1) - stats.trim_mean(zi, 0.1))
        test = stats.mannwhitneyu(zb, zi, alternative="greater")
        nominal = float(s["depth_um"])
        out.append(
            {
                "index": s["index"],
                "nominal_um": nominal,
                "measured_um": float(depth_um),
                "trimmed_mean_um": float(trimmed_um),
                "p_value": float(test.pvalue),
                "points_inside": int(len(zi)),
                "points_beside": int(len(zb)),
                "resolved": bool(test.pvalue < alpha and abs(depth_um - nominal) < 0.5 * nominal),
            }
        )
    return out


def fit_plane(points: NDArray) -> dict[str, Any]:
    """Least-squares plane (SVD) of (N, 3) points: unit normal, offset and the residual sigma (mm)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = p.mean(0)
    n = np.linalg.svd(p - c, full_matrices=False)[2][2]
    r = (p - c) @ n
    return {
        "normal": n.tolist(),
        "offset_mm": float(n @ c),
        "std_mm": float(r.std(ddof=3)),
        "peak_to_valley_mm": float(np.ptp(r)),
        "points": int(len(p)),
    }


def sphere_test(
    points: NDArray, radius_mm: float, centre_mm: NDArray, band_mm: float = 1.0
) -> dict[str, Any]:
    """A sphere of known radius (the plane/sphere test): the measured points (N, 3, mm) within ``band_mm``
    of the nominal sphere (``centre_mm``, the frame of ``points``) are fitted with :func:`fit_sphere`; reports
    the radius error, the sphere-fit residual sigma and how far the fitted centre lies from the nominal (mm).
    Leave out the surface the sphere stands on before calling (its points touch the sphere)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    near = np.abs(np.linalg.norm(p - centre_mm, axis=1) - radius_mm) < band_mm
    if near.sum() < 100:
        raise CalibrationError(
            f"sphere test: only {int(near.sum())} points within {band_mm} mm of the {radius_mm} mm sphere; "
            "is the sphere in view and lit?"
        )
    fit = fit_sphere(p[near])
    return {
        "true_radius_mm": float(radius_mm),
        **fit,
        "radius_error_mm": fit["radius_mm"] - float(radius_mm),
        "centre_offset_mm": float(np.linalg.norm(np.asarray(fit["centre_mm"]) - centre_mm)),
    }


def fit_sphere(points: NDArray) -> dict[str, Any]:
    """Least-squares sphere of (N, 3) points (algebraic start, then geometric refinement with SciPy)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol = np.linalg.lstsq(A, (p * p).sum(1), rcond=None)[0]
    c0, r0 = sol[:3], np.sqrt(sol[3] + sol[:3] @ sol[:3])
    fit = least_squares(lambda x: np.linalg.norm(p - x[:3], axis=1) - x[3], np.r_[c0, r0])
    res = fit.fun
    return {
        "centre_mm": fit.x[:3].tolist(),
        "radius_mm": float(fit.x[3]),
        "std_mm": float(res.std(ddof=4)),
        "points": int(len(p)),
    }
