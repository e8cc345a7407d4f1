"""Compiled kernels of :mod:`cell.analysis._point_grid` (numba): points binned into a grid, the nearest other
point of some of them, groups of points linked by a radius. Kept apart from the Python functions that call
them so that :mod:`cell.analysis.kernels` can load their ahead-of-time build without importing numba.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _cell_of(x: float, origin: float, h: float, n: int) -> int:
    return min(max(int(np.floor((x - origin) / h)), 0), n - 1)


@nb.njit(cache=True, nogil=True)
def _bin(points, origin, h, dims):
    """Counting sort of the points by their clamped grid cell (O(N), unlike argsort): ``start`` (cells + 1)
    and the point indices cell by cell. The point grid's bins, and the error map's visiting order."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    N = points.shape[0]
    key = np.empty(N, np.int64)
    start = np.zeros(nx * ny * nz + 1, np.int64)
    for n in range(N):
        i = _cell_of(points[n, 0], origin[0], h, nx)
        j = _cell_of(points[n, 1], origin[1], h, ny)
        k = _cell_of(points[n, 2], origin[2], h, nz)
        key[n] = (i * ny + j) * nz + k
        start[key[n] + 1] += 1
    for c in range(nx * ny * nz):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(N, np.int64)
    for n in range(N):
        order[fill[key[n]]] = n
        fill[key[n]] += 1
    return start, order


@nb.njit(cache=True, inline="always")
def _scan(points, px, py, pz, c, start, order, same, best):
    """Points of cell ``c``: the count at (px, py, pz) added to ``same``, the nearest other squared distance
    kept in ``best``."""
    for m in range(start[c], start[c + 1]):
        o = order[m]
        dx = points[o, 0] - px
        dy = points[o, 1] - py
        dz = points[o, 2] - pz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 == 0.0:
            same += 1
        elif d2 < best:
            best = d2
    return same, best


@nb.njit(cache=True, parallel=True)
def _nearest_other(points, queries, start, order, origin, h, dims):
    """For each query (an index into ``points``): how many points lie exactly at it (itself included) and
    the squared distance to the nearest point not at it (inf: none)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    rmax = max(nx, max(ny, nz))
    Q = queries.shape[0]
    n_same = np.zeros(Q, np.int64)
    best_d2 = np.full(Q, np.inf)
    for s in nb.prange(Q):
        q = queries[s]
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        ci = _cell_of(px, origin[0], h, nx)
        cj = _cell_of(py, origin[1], h, ny)
        ck = _cell_of(pz, origin[2], h, nz)
        same = 0
        best = np.inf
        for r in range(rmax + 1):  # the cells of ring r: Chebyshev distance r from the point's own
            for i in range(max(ci - r, 0), min(ci + r, nx - 1) + 1):
                for j in range(max(cj - r, 0), min(cj + r, ny - 1) + 1):
                    if abs(i - ci) == r or abs(j - cj) == r:
                        for k in range(max(ck - r, 0), min(ck + r, nz - 1) + 1):
                            c = (i * ny + j) * nz + k
                            same, best = _scan(points, px, py, pz, c, start, order, same, best)
                    else:  # a column through the ring's inside: only its two ends are on the ring
                        if ck - r >= 0:
                            c = (i * ny + j) * nz + ck - r
                            same, best = _scan(points, px, py, pz, c, start, order, same, best)
                        if ck + r <= nz - 1:
                            c = (i * ny + j) * nz + ck + r
                            same, best = _scan(points, px, py, pz, c, start, order, same, best)
            reach = r * h  # every point of a farther ring is more than this away
            if best <= reach * reach:
                break
        n_same[s] = same
        best_d2[s] = best
    return n_same, best_d2


@nb.njit(cache=True)
def _find(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@nb.njit(cache=True)
def _radius_labels(points, r2, start, order, origin, h, dims):
    """Union-find over the pairs no farther apart than sqrt(r2) (cells at least that wide: linked points
    lie in neighbouring cells); labels numbered by each group's lowest point index."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    N = points.shape[0]
    parent = np.arange(N)
    for a in range(N):
        px, py, pz = points[a, 0], points[a, 1], points[a, 2]
        ci = _cell_of(px, origin[0], h, nx)
        cj = _cell_of(py, origin[1], h, ny)
        ck = _cell_of(pz, origin[2], h, nz)
        for i in range(max(ci - 1, 0), min(ci + 1, nx - 1) + 1):
            for j in range(max(cj - 1, 0), min(cj + 1, ny - 1) + 1):
                for k in range(max(ck - 1, 0), min(ck + 1, nz - 1) + 1):
                    c = (i * ny + j) * nz + k
                    for m in range(start[c], start[c + 1]):
                        b = order[m]
                        if b <= a:
                            continue
                        dx = points[a, 0] - points[b, 0]
                        dy = points[a, 1] - points[b, 1]
                        dz = points[a, 2] - points[b, 2]
                        if dx * dx + dy * dy + dz * dz <= r2:
                            ra, rb = _find(parent, a), _find(parent, b)
                            if ra != rb:
                                parent[max(ra, rb)] = min(ra, rb)
    labels = np.empty(N, np.int64)
    n = 0
    for a in range(N):
        root = _find(parent, a)
        if root == a:
            labels[a] = n
            n += 1
        else:
            labels[a] = labels[root]
    return labels
