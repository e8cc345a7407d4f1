"""Multi-projection surface points (dissertation 2.4, Fig 2.17): the screen at two known positions.

A marker seen at pixel u with the screen at its first position gives the screen point W1 (the dot, known).
With the screen moved to its second known position, the same pixel sees the screen point W2, read from the
second image's identified markers through a local quadratic pixel -> screen map (the screen carries dots,
not a continuous code, so W2 is interpolated between the dots around u). The light reaching u left the pane
along the projection vector W = W1 - W2 (both points lie on it), so the surface point P is where the view
ray o + t U meets the line through W1 and W2 (closest approach of the two lines) and the normal is the
bisector V = unit(unit(W1 - P) - U). Unlike the single-camera search no CAD normal is assumed: the CAD only
seeds the marker identification.
"""

from __future__ import annotations

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


def multi_projection(
    law: ReflectionLaw,
    pixels: NDArray[np.float64],
    second_pixels: NDArray[np.float64],
    second_xy: NDArray[np.float64],
    second: MarkerScreen,
) -> SearchResult:
    """Surface points of ``law``'s markers (seen at ``pixels``, N x 2) from the second screen position:
    ``second_pixels`` / ``second_xy`` are the markers identified in that image (pixel, screen mm in {S}).
    ``ok`` is False where the second image has no markers around the pixel. ``iterations`` is 0 (no search);
    ``theta`` is the offset angle to the CAD normal at the found point."""
    w2 = screen_points_W(second.T_W_S, LocalQuadratic(second_pixels, second_xy, k=12)(pixels))
    w1 = law.p.markers
    t = closest_approach_t(law.p.origins, law.p.dirs, w1, w1 - w2)
    ok = law.ok & np.isfinite(t)
    t = np.where(ok, t, law.t0)
    points = law.p.origins + t[:, None] * law.p.dirs
    normals = unit(unit(w1 - points) - law.p.dirs)
    return SearchResult(t, points, normals, law.theta(t), np.zeros(len(t), dtype=np.int64), ok)
