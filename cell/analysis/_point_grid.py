"""Exact neighbour queries on a point cloud through a uniform grid (numba kernels in ``_point_grid_kernels``,
handed out by :mod:`cell.analysis.kernels`): the nearest other point of some of the points, and the groups of
points linked by a radius. The report's link radius and cluster regions and the pictures' point spacing use
them.

Written by hand because the library that does this, scipy's cKDTree (with scipy.sparse.csgraph for the
groups), costs 0.6-0.9 s of CPU to import -- as much as CloudCompare's whole comparison of 200k points --
while the error map's compiled kernels are loaded already. The answers are scipy's: the same distances (the
same sum of squares, then its root) and the same groups numbered the same way (by their lowest point index);
tests/test_analysis_point_grid.py compares them with cKDTree and connected_components.

Grid: points are counting-sorted into cubic cells of side ``h`` (a CSR: ``start`` per cell, point indices in
``order``). A point's nearest other point is searched ring by ring of cells around its own; after ring r
every point not yet seen is at least ``r * h`` away, so the search stops once the best is closer. Radius
groups use cells at least as wide as the radius: linked points lie in neighbouring cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.analysis import kernels
from cell.geometry import bounding_box

_MAX_CELLS = 4_000_000


@dataclass(frozen=True)
class PointGrid:
    """Points binned into a uniform grid (mm): origin, cell side, cells per axis, CSR of point indices."""

    points: NDArray[np.float64]
    origin: NDArray[np.float64]
    h: float
    dims: NDArray[np.int64]
    start: NDArray[np.int64]
    order: NDArray[np.int64]


def point_grid(points_mm: NDArray, h_min: float = 0.0, per_cell: float = 4.0) -> PointGrid:
    """Bin ``points_mm`` (N, 3) into cells of about ``per_cell`` points on a surface, at least ``h_min``
    wide, at most 8 N and :data:`_MAX_CELLS` cells."""
    p = np.ascontiguousarray(points_mm, dtype=np.float64).reshape(-1, 3)
    lo, hi = bounding_box(p)
    span = np.maximum(hi - lo, 1e-9)
    # a cloud of a surface: N points over an area of about the box's largest face
    area = float(np.sort(span)[1:].prod())
    h = max(float(np.sqrt(per_cell * area / max(len(p), 1))), h_min, 1e-9)
    max_cells = min(_MAX_CELLS, 8 * len(p) + 4096)  # most cells of a surface's box are empty: cap them
    while np.prod(np.floor(span / h) + 1) > max_cells:
        h *= 1.25
    dims = (np.floor(span / h) + 1).astype(np.int64)
    start, order = kernels.get("_bin")(p, lo, h, dims)
    return PointGrid(p, lo, h, dims, start, order)


def nearest_other(
    grid: PointGrid, queries: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """For the points ``queries`` (indices): the number of points exactly at each (itself included) and the
    distance (mm) to the nearest point elsewhere (inf when there is none)."""
    q = np.ascontiguousarray(queries, dtype=np.int64)
    # queries visited cell by cell: neighbouring queries scan the same cells while they are in cache
    cell = np.clip(np.floor((grid.points[q] - grid.origin) / grid.h).astype(np.int64), 0, grid.dims - 1)
    by_cell = np.argsort((cell[:, 0] * grid.dims[1] + cell[:, 1]) * grid.dims[2] + cell[:, 2], kind="stable")
    n_same, d2 = np.empty(len(q), np.int64), np.empty(len(q))
    n_same[by_cell], d2[by_cell] = kernels.get("_nearest_other")(
        grid.points, q[by_cell], grid.start, grid.order, grid.origin, grid.h, grid.dims
    )
    return n_same, np.sqrt(d2)


def radius_groups(points_mm: NDArray, radius_mm: float) -> NDArray[np.int64]:
    """Group label of each point (N, 3): points no farther apart than ``radius_mm`` share a group, and so do
    chains of them (the connected components of scipy's ``query_pairs`` graph, numbered alike)."""
    p = np.ascontiguousarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    grid = point_grid(p, h_min=max(float(radius_mm), 0.0))
    return kernels.get("_radius_labels")(
        p, float(radius_mm) ** 2, grid.start, grid.order, grid.origin, grid.h, grid.dims
    )
