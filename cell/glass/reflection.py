"""Reflection search along a view ray (dissertation 2.3.3-2.3.4, eq 2.13), vectorised over markers.

For a marker S (world mm) seen along the view ray M(t) = o + t U, the reflection law asks for the normal
V_req(t) = unit(unit(S - M) - U), the bisector of the reversed view ray and the ray to the marker. The CAD
supplies the normal V_cad(t) of the designed surface under M(t) (the Phong normal where the line through M
along the seed normal meets the CAD). The surface point is where the offset angle theta(t) between them is
smallest (zero when the made surface has the designed normal there): a shape error that moves the surface
along its normal leaves its normal unchanged, which is the assumption of the single-camera method.

Search interval: eq 2.13 bounds the travel on the CAD by L = 2 Delta cot(beta) for the largest expected
surface error Delta and the grazing angle beta; along the ray that is t0 +- 2 Delta / cos(i), i the incidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.glass.surface import SmoothSurface, unit

_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0
_LIFT_MM = 30.0  # the CAD is looked up from this far above M along the seed normal


@dataclass(frozen=True)
class RaySearchProblem:
    """N markers: view-ray origins and unit directions (N, 3), marker points (N, 3), all world mm."""

    origins: NDArray[np.float64]
    dirs: NDArray[np.float64]
    markers: NDArray[np.float64]


@dataclass(frozen=True)
class SearchResult:
    """Per marker: ray parameter t (mm), surface point, reflection-law normal, final offset angle (rad),
    evaluations of theta used, and whether the seed ray hit the CAD."""

    t: NDArray[np.float64]
    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    theta: NDArray[np.float64]
    iterations: NDArray[np.int64]
    ok: NDArray[np.bool_]


class ReflectionLaw:
    """theta(t) for a batch of markers against a CAD surface, seeded by the view rays' CAD intersections."""

    def __init__(self, problem: RaySearchProblem, cad: SmoothSurface) -> None:
        self.p = problem
        self.cad = cad
        seed = cad.cast(problem.origins, problem.dirs)
        self.ok = seed.hit
        self.t0 = np.where(self.ok, seed.distance, 0.0)
        n = np.where(self.ok[:, None], seed.normal, np.array([0.0, 0.0, 1.0]))
        self.seed_normal = np.where((np.einsum("ij,ij->i", n, problem.dirs) > 0)[:, None], -n, n)
        self.cos_i = np.abs(np.einsum("ij,ij->i", self.seed_normal, problem.dirs))

    def bracket(self, max_error_mm: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Eq 2.13 search interval on the ray: t0 +- 2 Delta / cos(i)."""
        half = 2.0 * max_error_mm / np.maximum(self.cos_i, 0.1)
        return self.t0 - half, self.t0 + half

    def required_normal(self, t: NDArray[np.float64], idx: NDArray[np.int64] | slice = slice(None)):
        """Bisector normal at M(t) that reflects the view ray onto the marker."""
        m = self.p.origins[idx] + t[:, None] * self.p.dirs[idx]
        return unit(unit(self.p.markers[idx] - m) - self.p.dirs[idx])

    def cad_normal(self, t: NDArray[np.float64], idx: NDArray[np.int64] | slice = slice(None)):
        """Designed-surface normal under M(t) (NaN where the lookup misses the CAD)."""
        m = self.p.origins[idx] + t[:, None] * self.p.dirs[idx]
        n0 = self.seed_normal[idx]
        hit = self.cad.cast(m + _LIFT_MM * n0, -n0)
        return np.where((np.einsum("ij,ij->i", hit.normal, n0) < 0)[:, None], -hit.normal, hit.normal)

    def theta(self, t: NDArray[np.float64], idx: NDArray[np.int64] | slice = slice(None)) -> NDArray:
        """Offset angle (rad) between the required and the CAD normal; inf where the CAD lookup misses."""
        a, b = self.required_normal(t, idx), self.cad_normal(t, idx)
        s = np.linalg.norm(np.cross(a, b), axis=1)
        c = np.einsum("ij,ij->i", a, b)
        return np.nan_to_num(np.arctan2(s, c), nan=np.inf)

    def result(self, t: NDArray[np.float64], iterations: NDArray[np.int64]) -> SearchResult:
        return SearchResult(
            t,
            self.p.origins + t[:, None] * self.p.dirs,
            self.required_normal(t),
            self.theta(t),
            iterations,
            self.ok.copy(),
        )


def golden_minimize(
    f,
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    active: NDArray[np.bool_],
    length_tol: float,
    value_tol: float = 0.0,
    max_iter: int = 80,
):
    """Vectorised golden-section minimisation of ``f(t, idx)`` on [a, b] for every active entry; an entry
    stops when its interval is shorter than ``length_tol`` or its best value is below ``value_tol``.
    Returns the best t and the number of evaluations of f per entry."""
    a, b = a.copy(), b.copy()
    c = b - _GOLDEN * (b - a)
    d = a + _GOLDEN * (b - a)
    every = np.arange(len(a))
    fc, fd = f(c, every), f(d, every)
    its = np.full(len(a), 2, dtype=np.int64)
    active = active.copy()
    for _ in range(max_iter):
        active &= ((b - a) > length_tol) & (np.minimum(fc, fd) > value_tol)
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        left = fc[idx] < fd[idx]  # the minimum lies in [a, d]: shrink from the right
        ia, ib = idx[left], idx[~left]
        b[ia], d[ia], fd[ia] = d[ia], c[ia], fc[ia]
        c[ia] = b[ia] - _GOLDEN * (b[ia] - a[ia])
        a[ib], c[ib], fc[ib] = c[ib], d[ib], fd[ib]
        d[ib] = a[ib] + _GOLDEN * (b[ib] - a[ib])
        if len(ia):
            fc[ia] = f(c[ia], ia)
        if len(ib):
            fd[ib] = f(d[ib], ib)
        its[idx] += 1
    return np.where(fc < fd, c, d), its


def golden_section(
    law: ReflectionLaw,
    max_error_mm: float,
    angle_tol_rad: float,
    length_tol_mm: float = 2e-4,
    max_iter: int = 80,
) -> SearchResult:
    """Golden-section search of theta on the eq 2.13 interval (2.3.4); each marker stops when theta is below
    ``angle_tol_rad`` or its interval is shorter than ``length_tol_mm``. ``iterations`` counts theta
    evaluations per marker."""
    a, b = law.bracket(max_error_mm)
    t, its = golden_minimize(law.theta, a, b, law.ok, length_tol_mm, angle_tol_rad, max_iter)
    return law.result(t, its)


def stepwise(
    law: ReflectionLaw,
    step_mm: float,
    angle_tol_rad: float,
    length_tol_mm: float = 2e-4,
    max_iter: int = 5000,
) -> SearchResult:
    """Step-wise iterative search (2.3.3): walk from the CAD seed in steps of ``step_mm`` while theta falls;
    when it rises, turn back with half the step; stop at theta below ``angle_tol_rad`` or a step below
    ``length_tol_mm``. ``iterations`` counts theta evaluations per marker."""
    n = len(law.t0)
    t = law.t0.copy()
    f = law.theta(t)
    h = np.full(n, step_mm)
    its = np.ones(n, dtype=np.int64)
    active = law.ok.copy()
    for _ in range(max_iter):
        active &= (np.abs(h) > length_tol_mm) & (f > angle_tol_rad)
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        tn = t[idx] + h[idx]
        fn = law.theta(tn, idx)
        its[idx] += 1
        better = fn < f[idx]
        t[idx[better]], f[idx[better]] = tn[better], fn[better]
        h[idx[~better]] *= -0.5
    return law.result(t, its)


def exhaustive(law: ReflectionLaw, max_error_mm: float, step_mm: float) -> SearchResult:
    """Reference: theta on every ``step_mm`` of the eq 2.13 interval, the smallest wins (slow, for tests)."""
    a, b = law.bracket(max_error_mm)
    n_steps = int(np.ceil(np.max(b - a) / step_mm)) + 1
    best_t = law.t0.copy()
    best_f = np.full(len(a), np.inf)
    for k in range(n_steps):
        t = np.minimum(a + k * step_mm, b)
        f = law.theta(t)
        better = f < best_f
        best_t[better], best_f[better] = t[better], f[better]
    return law.result(best_t, np.full(len(a), n_steps, dtype=np.int64))
