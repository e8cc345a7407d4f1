"""The figures of VDI/VDE 2634 Part 2 from measured points (mm, any one Cartesian frame).

- PF, probing error (form): range of the radial residuals of a least-squares sphere fit.
- PS, probing error (size): least-squares diameter minus the calibrated diameter.
- SD, sphere-spacing error: least-squares centre distance of a ball bar minus the calibrated distance.
- F, flatness measurement error: range of the residuals to a least-squares plane.

Outliers: the guideline lets up to 0.3 % of the points go. Here the ``floor(0.003 * N)`` points with the
largest absolute residual of the all-point fit are dropped, the fit is repeated on the rest, and the figures
are taken from that second fit and its points. Sphere fits are SciPy's ``least_squares`` on the geometric
(orthogonal) residual, started from the algebraic fit; the plane is the orthogonal-distance least-squares
plane, which the SVD of the centred points gives exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

OUTLIER_FRACTION = 0.003  # VDI/VDE 2634-2: at most 0.3 % of the points may be excluded
MIN_POINTS = 20


class FitError(ValueError):
    """Too few or degenerate points for a fit."""


@dataclass(frozen=True)
class SphereFit:
    """A least-squares sphere: centre (mm), radius (mm), the points' radial residuals (mm, outward +) and how
    many points were excluded before the final fit."""

    centre: NDArray[np.float64]
    radius: float
    residuals: NDArray[np.float64]
    n_used: int
    n_excluded: int

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius

    @property
    def form_range(self) -> float:
        """PF: max minus min radial residual of the points used (mm)."""
        return float(self.residuals.max() - self.residuals.min())

    @property
    def rms(self) -> float:
        """Root mean square of the residuals (mm): the noise under the form range."""
        return float(np.sqrt(np.mean(self.residuals**2)))


@dataclass(frozen=True)
class PlaneFit:
    """A least-squares plane: a point on it (the centroid), the unit normal, the residuals (mm) and how many
    points were excluded before the final fit."""

    point: NDArray[np.float64]
    normal: NDArray[np.float64]
    residuals: NDArray[np.float64]
    n_used: int
    n_excluded: int

    @property
    def form_range(self) -> float:
        """F: max minus min residual of the points used (mm)."""
        return float(self.residuals.max() - self.residuals.min())

    @property
    def rms(self) -> float:
        """Root mean square of the residuals (mm)."""
        return float(np.sqrt(np.mean(self.residuals**2)))


def _points(points: ArrayLike) -> NDArray[np.float64]:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < MIN_POINTS:
        raise FitError(f"{len(p)} finite points; a fit needs at least {MIN_POINTS}")
    return p


def n_excluded(n_points: int, fraction: float = OUTLIER_FRACTION) -> int:
    """How many points the guideline's exclusion rule drops from ``n_points``."""
    return int(math.floor(fraction * n_points))


def _sphere_lsq(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    # algebraic fit |p|^2 = 2 c.p + (r^2 - |c|^2): linear, a good start for the geometric fit
    A = np.column_stack([2.0 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, (p**2).sum(axis=1), rcond=None)
    c0 = sol[:3]
    r0 = math.sqrt(max(sol[3] + c0 @ c0, 1e-12))
    shift = p.mean(axis=0)  # fit about the centroid: better conditioned far from the origin
    q = p - shift

    def residual(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.linalg.norm(q - x[:3], axis=1) - x[3]

    res = least_squares(residual, np.r_[c0 - shift, r0], method="lm", xtol=1e-14, ftol=1e-14)
    if not res.success:
        raise FitError(f"sphere fit did not converge: {res.message}")
    return res.x[:3] + shift, float(res.x[3])


def fit_sphere(points: ArrayLike, outlier_fraction: float = OUTLIER_FRACTION) -> SphereFit:
    """Least-squares sphere through ``points`` (N, 3) after the guideline's outlier exclusion."""
    p = _points(points)
    centre, radius = _sphere_lsq(p)
    k = n_excluded(len(p), outlier_fraction)
    if k:
        r = np.abs(np.linalg.norm(p - centre, axis=1) - radius)
        p = p[np.argsort(r)[: len(p) - k]]
        centre, radius = _sphere_lsq(p)
    residuals = np.linalg.norm(p - centre, axis=1) - radius
    return SphereFit(centre, radius, residuals, len(p), k)


def _plane_lsq(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    centroid = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - centroid, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise FitError("points are collinear; a plane needs points spread in two directions")
    return centroid, vt[2]


def fit_plane(points: ArrayLike, outlier_fraction: float = OUTLIER_FRACTION) -> PlaneFit:
    """Least-squares (orthogonal distance) plane through ``points`` (N, 3) after the outlier exclusion."""
    p = _points(points)
    point, normal = _plane_lsq(p)
    k = n_excluded(len(p), outlier_fraction)
    if k:
        d = np.abs((p - point) @ normal)
        p = p[np.argsort(d)[: len(p) - k]]
        point, normal = _plane_lsq(p)
    return PlaneFit(point, normal, (p - point) @ normal, len(p), k)


def probing_form(fit: SphereFit) -> float:
    """PF (mm)."""
    return fit.form_range


def probing_size(fit: SphereFit, calibrated_diameter_mm: float) -> float:
    """PS (mm): measured minus calibrated diameter."""
    return fit.diameter - calibrated_diameter_mm


def sphere_spacing(fit_a: SphereFit, fit_b: SphereFit, calibrated_distance_mm: float) -> float:
    """SD (mm): measured minus calibrated centre distance of two spheres."""
    return float(np.linalg.norm(fit_a.centre - fit_b.centre)) - calibrated_distance_mm


def flatness(fit: PlaneFit) -> float:
    """F (mm)."""
    return fit.form_range
