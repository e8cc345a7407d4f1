"""Multi-projection surface points (dissertation 2.4, Fig 2.17): the screen at two known positions.

A marker seen at pixel u with the screen at its first position gives the screen point W1 (the dot, known).
With the screen moved to its second known position, the same pixel sees the screen point W2, read from the
second image's identified markers through a local quadratic pixel -> screen map (the screen carries dots,
not a continuous code, so W2 is interpolated between the dots around u). The light reaching u left the pane
along the projection vector W = W1 - W2 (both points lie on it), so the surface point P is where the view
ray o + t U meets the line through W1 and W2 (closest approach of the two lines) and the normal is the
bisector V = unit(unit(W1 - P) - U). Unlike the single-camera search no CAD normal is assumed: the CAD only
seeds the marker identification.

How well the two screen points fit the ray is kept per marker (:class:`ProjectionFit`): a point seen by this
one camera only is then judged by its own geometry (cell.glass.consistency.check_projection) instead of being
left unconfirmed as a single-camera golden-section point must be.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.contracts import MarkerScreen
from cell.glass.calibration import LocalQuadratic
from cell.glass.reflection import ReflectionLaw, SearchResult
from cell.glass.surface import unit


def screen_points_W(T_W_S: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """World points (N, 3) of screen-plane points (N, 2, mm in {S})."""
    return xy[:, 0:1] * T_W_S[:3, 0] + xy[:, 1:2] * T_W_S[:3, 1] + T_W_S[:3, 3]


def closest_approach_t(
    o: NDArray[np.float64], u: NDArray[np.float64], a: NDArray[np.float64], w: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Parameter t on the lines o + t u where they pass closest to the lines a + s w (N each)."""
    r = o - a
    uu, uw, ww = (np.einsum("ij,ij->i", x, y) for x, y in ((u, u), (u, w), (w, w)))
    ur, wr = np.einsum("ij,ij->i", u, r), np.einsum("ij,ij->i", w, r)
    den = uu * ww - uw * uw
    with np.errstate(invalid="ignore", divide="ignore"):
        return (uw * wr - ww * ur) / den


@dataclass(frozen=True)
class ProjectionFit:
    """Per marker: ``miss_mm``, the closest distance of the view ray and the W1-W2 line (0 for exact data);
    ``lever`` = |P - W1| / |W1 - W2|, how far an error of W2 moves the line at P (mm per mm);
    ``sin_angle`` of the ray and the line (a small angle pins P poorly along the ray)."""

    miss_mm: NDArray[np.float64]
    lever: NDArray[np.float64]
    sin_angle: NDArray[np.float64]


def multi_projection(
    law: ReflectionLaw,
    pixels: NDArray[np.float64],
    second_pixels: NDArray[np.float64],
    second_xy: NDArray[np.float64],
    second: MarkerScreen,
) -> tuple[SearchResult, ProjectionFit]:
    """Surface points of ``law``'s markers (seen at ``pixels``, N x 2) from the second screen position:
    ``second_pixels`` / ``second_xy`` are the markers identified in that image (pixel, screen mm in {S}).
    ``ok`` is False where the second image has no markers around the pixel. ``iterations`` is 0 (no search);
    ``theta`` is the offset angle to the CAD normal at the found point. Also the fit of each marker's two
    screen points to its ray."""
    w2 = screen_points_W(second.T_W_S, LocalQuadratic(second_pixels, second_xy, k=12)(pixels))
    w1 = law.p.markers
    t = closest_approach_t(law.p.origins, law.p.dirs, w1, w1 - w2)
    ok = law.ok & np.isfinite(t)
    t = np.where(ok, t, law.t0)
    points = law.p.origins + t[:, None] * law.p.dirs
    normals = unit(unit(w1 - points) - law.p.dirs)
    w = w1 - w2
    w_len = np.linalg.norm(w, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        w_dir = w / w_len[:, None]
        s = np.einsum("ij,ij->i", points - w1, w_dir)
        miss = np.linalg.norm(points - (w1 + s[:, None] * w_dir), axis=1)
        lever = np.linalg.norm(points - w1, axis=1) / w_len
    sin_angle = np.linalg.norm(np.cross(law.p.dirs, np.nan_to_num(w_dir)), axis=1)
    fit = ProjectionFit(np.where(ok, miss, np.nan), np.where(ok, lever, np.nan), sin_angle)
    result = SearchResult(t, points, normals, law.theta(t), np.zeros(len(t), dtype=np.int64), ok)
    return result, fit
