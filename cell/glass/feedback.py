"""Multi-camera feedback of the back-imaging rig (dissertation 3.4, Figs 3.15-3.17).

The primary camera's search gives a point P on its view ray U1 and a normal V1. Another camera k looks at P
along U_k = unit(P - C_k); the screen point W_k it sees there comes from its own identified markers (a local
quadratic map pixel -> screen through its image); the reflection law gives its normal V_k. If P were the
surface point, V_k = V1. Otherwise the dissertation averages the normals and moves P along U1 to suit the
average; iterated, that fixed point only converges for some camera layouts, so here P is moved to where the
cameras agree best: the point on U1 that minimises the spread of the normals of all cameras used so far
(golden section on the eq 2.13 interval), which is the fixed point the averaging aims at. Cameras are added
one at a time until the averaged normal moves less than the threshold (Fig 3.17).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.glass.calibration import LocalQuadratic, ViewVectorCalibration
from cell.glass.reflection import ReflectionLaw, SearchResult, golden_minimize
from cell.glass.surface import unit


@dataclass
class FeedbackCamera:
    """A camera that can confirm a point: its calibration and its pixel -> screen (mm, {S}) marker map."""

    calib: ViewVectorCalibration
    screen_map: LocalQuadratic

    def normals(self, points_W: NDArray[np.float64], T_W_S: NDArray[np.float64]) -> NDArray[np.float64]:
        """Reflection-law normals (N, 3) this camera measures at ``points_W``; NaN where it cannot see
        them."""
        uv = self.calib.project(points_W)
        w, h = self.calib.resolution
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
        out = np.full((len(points_W), 3), np.nan)
        if not np.any(inside):
            return out
        sxy = self.screen_map(uv[inside])
        s_W = sxy[:, 0:1] * T_W_S[:3, 0] + sxy[:, 1:2] * T_W_S[:3, 1] + T_W_S[:3, 3]
        m = points_W[inside]
        out[inside] = unit(unit(s_W - m) - unit(m - self.calib.centre_mm))
        return out


@dataclass(frozen=True)
class FeedbackResult:
    """Per point: final position and averaged normal; ``n_cameras`` whose normal exists at the final point
    (incl. the primary); the normal's change when the last camera was added (rad); ``residual`` = sum of
    squared angles of those normals to their mean (rad^2, the minimised cost); ``curvature`` = its second
    derivative along the ray at the optimum (rad^2/mm^2, how sharply the cameras pin the depth; 0 for
    a single camera) and the position after each number of cameras."""

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    n_cameras: NDArray[np.int64]
    last_change: NDArray[np.float64]
    residual: NDArray[np.float64]
    curvature: NDArray[np.float64]
    history: NDArray[np.float64]


def _spread(normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sum of squared angles (rad^2, small-angle) of each camera's normal to their mean; (C, N, 3) -> (N,)."""
    mean = unit(np.nanmean(normals, axis=0))
    d = normals - mean[None]
    return np.nansum(np.einsum("cni,cni->cn", d, d), axis=0)


def feedback(
    law: ReflectionLaw,
    primary: SearchResult,
    cameras: list[FeedbackCamera],
    T_W_S: NDArray[np.float64],
    max_error_mm: float,
    tol_rad: float,
    length_tol_mm: float = 2e-4,
    curvature_step_mm: float = 0.05,
) -> FeedbackResult:
    """Confirm/correct the primary camera's points with ``cameras`` in order (3.4). The curvature of the
    cost is a central difference over +-``curvature_step_mm`` (the cost is quadratic near its minimum)."""
    origins, dirs = law.p.origins, law.p.dirs
    t = primary.t.copy()
    normal = primary.normals.copy()
    n_cams = np.ones(len(t), dtype=np.int64)
    change = np.full(len(t), np.nan)
    active = primary.ok.copy()
    history = [primary.points.copy()]
    residual = np.zeros(len(t))
    curvature = np.zeros(len(t))
    a, b = law.bracket(max_error_mm)
    h = curvature_step_mm
    for k in range(len(cameras)):
        sees = np.all(np.isfinite(cameras[k].normals(origins + t[:, None] * dirs, T_W_S)), axis=1)
        step = active & sees
        used = cameras[: k + 1]

        def normals_at(
            tt: NDArray[np.float64], idx: NDArray[np.int64], used: list[FeedbackCamera] = used
        ) -> NDArray[np.float64]:
            m = origins[idx] + tt[:, None] * dirs[idx]
            return np.stack([law.required_normal(tt, idx)] + [c.normals(m, T_W_S) for c in used])

        def cost(tt: NDArray[np.float64], idx: NDArray[np.int64]) -> NDArray[np.float64]:
            return _spread(normals_at(tt, idx))

        t_new, _ = golden_minimize(cost, a, b, step, length_tol_mm)
        idx = np.flatnonzero(step)
        ns = normals_at(t_new[idx], idx)
        # where no other camera's normal exists at the minimum, the cost was the primary's alone (flat):
        # the move means nothing, so those points keep their position and wait for the next camera
        confirmed = np.sum(np.all(np.isfinite(ns), axis=2), axis=0) >= 2
        idx, ns = idx[confirmed], ns[:, confirmed]
        v = unit(np.nanmean(ns, axis=0))
        old = normal[idx]
        delta = np.arctan2(np.linalg.norm(np.cross(v, old), axis=1), np.einsum("ij,ij->i", v, old))
        t[idx], normal[idx], change[idx] = t_new[idx], v, delta
        residual[idx] = _spread(ns)
        curvature[idx] = (cost(t[idx] + h, idx) - 2 * residual[idx] + cost(t[idx] - h, idx)) / h**2
        n_cams[idx] = np.sum(np.all(np.isfinite(ns), axis=2), axis=0)
        active[idx[delta < tol_rad]] = False  # settled: no more cameras for these points
        history.append(origins + t[:, None] * dirs)
    return FeedbackResult(
        origins + t[:, None] * dirs, normal, n_cams, change, residual, curvature, np.stack(history)
    )
