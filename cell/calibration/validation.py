"""Validation of a sensor calibration (dissertation 5.1): the flat test at a known height (Table 5.1), the
gauge slot test against the gauge's certificate (Fig 5.4: which slot depths are resolved) and plane / sphere
fits of measured clouds."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy import stats
from scipy.optimize import least_squares

from cell.config import read_yaml, validate
from cell.errors import CalibrationError, ConfigError
from cell.schema import Strict
from cell.sensing.triangulate import SensorCloud

if TYPE_CHECKING:
    import trimesh


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


class GaugeSlot(Strict):
    """One slot of the gauge: its certified depth (um, with the certificate's uncertainty) and where it is in
    the gauge's frame (mm; the slot runs across the top face)."""

    depth_um: float = Field(ge=0, lt=1000)
    uncertainty_um: float = Field(0.0, ge=0, lt=100)
    x_range_mm: tuple[float, float]
    y_range_mm: tuple[float, float]


class GaugeCertificate(Strict):
    """The slot gauge's certificate (``recipes/parts/gauge.certificate.yaml``): the certified slot depths of
    dissertation Fig 5.4 and the slot layout of its drawing. ``mesh`` is its CAD, relative to the file."""

    name: str
    serial: str = Field(min_length=1)
    laboratory: str = ""
    date: str = ""
    mesh: Path
    top_z_mm: float = Field(gt=0)
    slots: list[GaugeSlot] = Field(min_length=1)


def load_gauge_certificate(path: str | Path) -> GaugeCertificate:
    """Read a gauge certificate; ConfigError naming the file and field when it is wrong. The mesh path is
    made absolute (relative to the certificate)."""
    cert = validate(GaugeCertificate, read_yaml(path), path)
    cert.mesh = (Path(path).parent / cert.mesh).resolve()
    if not cert.mesh.is_file():
        raise ConfigError(
            f"the gauge's mesh {cert.mesh} does not exist; give its path relative to the certificate",
            path=str(path),
            field="mesh",
        )
    return cert


def slot_test(
    points_P: NDArray,
    slots: Sequence[GaugeSlot],
    margin_mm: float = 2.0,
    band_mm: float = 6.0,
    alpha: float = 0.001,
) -> list[dict[str, Any]]:
    """Per gauge slot (gauge frame mm, z up): the depth after ISO 5436-1's groove evaluation (its idea, not
    its W/3 regions). A plane is fitted to the two bands of top face beside the slot (``band_mm`` wide,
    ``margin_mm`` clear of its walls, so that a placement error up to the margin neither puts wall nor floor
    into them); the depth is the plane's height over the slot floor (its middle, ``margin_mm`` in from each
    wall): median and 10 % trimmed mean of the residuals, so that a few stray points cannot fake or hide a
    slot. The fitted plane takes out the tilt that the robot pose and hand-eye leave (0.05 deg is 9 um over
    the 10 mm slot) even where one side of a slot has fewer points than the other (a difference of medians
    would not). Resolved: the band residuals are significantly above the floor's (Mann-Whitney U, one-sided,
    p < ``alpha``; no normality assumed) and the median depth is within half the certified depth of it."""
    p = np.asarray(points_P, dtype=np.float64)
    out = []
    for i, s in enumerate(slots):
        (x0, x1), (y0, y1) = s.x_range_mm, s.y_range_mm
        iny = (p[:, 1] > y0 + margin_mm) & (p[:, 1] < y1 - margin_mm)
        inside = iny & (p[:, 0] > x0 + margin_mm) & (p[:, 0] < x1 - margin_mm)
        beside = iny & (
            ((p[:, 0] > x0 - margin_mm - band_mm) & (p[:, 0] < x0 - margin_mm))
            | ((p[:, 0] > x1 + margin_mm) & (p[:, 0] < x1 + margin_mm + band_mm))
        )
        if inside.sum() < 10 or beside.sum() < 10:
            raise CalibrationError(
                f"slot test: slot {i} has {inside.sum()} points inside and {beside.sum()} "
                "beside it; is the gauge in view?"
            )
        surround = _robust_plane(p[beside])
        rb = p[beside, 2] - surround(p[beside])
        ri = p[inside, 2] - surround(p[inside])
        depth_um = -1000 * float(np.median(ri))
        trimmed_um = 1000 * float(stats.trim_mean(rb, 0.1) - stats.trim_mean(ri, 0.1))
        test = stats.mannwhitneyu(rb, ri, alternative="greater")
        nominal = s.depth_um
        out.append(
            {
                "index": i,
                "nominal_um": nominal,
                "certificate_uncertainty_um": s.uncertainty_um,
                "measured_um": depth_um,
                "trimmed_mean_um": trimmed_um,
                "surround_sigma_um": 1000 * float(1.4826 * np.median(np.abs(rb - np.median(rb)))),
                "p_value": float(test.pvalue),
                "points_inside": int(inside.sum()),
                "points_beside": int(beside.sum()),
                "resolved": bool(test.pvalue < alpha and abs(depth_um - nominal) < 0.5 * nominal),
            }
        )
    return out


def _robust_plane(points: NDArray) -> Callable[[NDArray], NDArray]:
    """z = a x + b y + c fitted by SciPy least squares with a soft-L1 loss (stray points weigh little);
    returns the plane's height at given (N, 3) points."""
    x, y, z = points.T
    x0, y0 = x.mean(), y.mean()
    A = np.column_stack([x - x0, y - y0, np.ones_like(x)])
    start = np.linalg.lstsq(A, z, rcond=None)[0]
    scale = max(1.4826 * float(np.median(np.abs(z - A @ start))), 1e-6)

    def residuals(c: NDArray[np.float64]) -> NDArray[np.float64]:
        return A @ c - z

    coef = least_squares(residuals, start, loss="soft_l1", f_scale=scale).x
    return lambda q: coef[0] * (q[:, 0] - x0) + coef[1] * (q[:, 1] - y0) + coef[2]


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


def sphere_mesh_lsq(radius_mm: float, subdivisions: int = 6) -> trimesh.Trimesh:
    """A closed icosphere centred on the origin whose surface's least-squares sphere has ``radius_mm`` (mm):
    its vertices stand out by the facets' mean depth (the mesh scaled by the inverse of its
    :func:`mean_surface_radius`), so the flat facets deviate both ways, by under +-0.6 um at 12.7 mm with 6
    subdivisions. With its vertices on the sphere instead, the surface's least-squares radius is short by
    0.57 um there (6 subdivisions) and by 2.3 um at 12.5 mm with 5: what a perfect sensor would measure."""
    import trimesh  # late: the calibration package does not load trimesh until a mesh is built

    unit = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return unit.apply_scale(radius_mm / mean_surface_radius(unit))


def mean_surface_radius(mesh: trimesh.Trimesh) -> float:
    """Area-weighted mean distance (mesh units) of the surface from the origin: the least-squares sphere's
    radius of a closed mesh symmetric about the origin. Three-point rule on each facet (exact for quadratics;
    the distance varies by 1e-4 of itself over a facet of an icosphere of 6 subdivisions)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    rule = np.full((3, 3), 1 / 6) + np.eye(3) / 2  # barycentric (2/3, 1/6, 1/6) and its permutations
    dist = np.linalg.norm(np.einsum("qk,fkd->fqd", rule, tri), axis=2).mean(axis=1)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    return float(area @ dist / area.sum())


def fit_sphere(points: NDArray) -> dict[str, Any]:
    """Least-squares sphere of (N, 3) points (algebraic start, then geometric refinement with SciPy)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol = np.linalg.lstsq(A, (p * p).sum(1), rcond=None)[0]
    c0, r0 = sol[:3], np.sqrt(sol[3] + sol[:3] @ sol[:3])

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.linalg.norm(p - x[:3], axis=1) - x[3]

    fit = least_squares(residuals, np.r_[c0, r0])
    res = fit.fun
    return {
        "centre_mm": fit.x[:3].tolist(),
        "radius_mm": float(fit.x[3]),
        "std_mm": float(res.std(ddof=4)),
        "points": int(len(p)),
    }
