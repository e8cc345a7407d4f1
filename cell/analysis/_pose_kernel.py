"""Compiled per-point pose uncertainty of a merged cloud (numba): u^2 = l C l^T over the views a point has.

A merged point is the ``shares``-weighted mean of its views' points, so its motion along the normal under
the views' pose errors x is l x with l = s (x) r - r B (s: its shares, r: its row, B: the alignment's map;
:func:`cell.analysis.uncertainty.pose_uncertainty_of_points`). Expanded over the 6x6 blocks,

    l C l^T = sum_ij s_i s_j r C_ij r^T - 2 sum_i s_i r D_i r^T + r E r^T,   D = B C, E = B C B^T,

and only the views with a share enter: one or two for most points of a dozen views. numpy's dense
l C l^T (a (M, 6n) by (6n, 6n) product) did 30 times the arithmetic: 5 s of CPU for the pillar's two million
merged points, a quarter of the work after the last frame (docs/benchmarks.md). Written by hand because no
library evaluates a block-sparse quadratic form per row.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray


@nb.njit(cache=True, inline="always")
def _form(r, A, row0, col0):
    """r A[row0:row0+6, col0:col0+6] r^T for one row r (6,)."""
    q = 0.0
    for x in range(6):
        acc = 0.0
        for y in range(6):
            acc += A[row0 + x, col0 + y] * r[y]
        q += r[x] * acc
    return q


@nb.njit(cache=True, nogil=True)  # nogil: a pool's threads compute chunks side by side
def _pose_variance(shares, rows, C, D, E, aligned, out):
    m, n = shares.shape
    seen = np.empty(n, np.int64)
    for p in range(m):
        k = 0
        for i in range(n):
            if shares[p, i] != 0.0:
                seen[k] = i
                k += 1
        r = rows[p]
        var = _form(r, E, 0, 0) if aligned else 0.0
        for a in range(k):
            i = seen[a]
            si = shares[p, i]
            var += si * si * _form(r, C, 6 * i, 6 * i)
            for b in range(a + 1, k):  # C is symmetric: (i, j) and (j, i) alike
                j = seen[b]
                var += 2.0 * si * shares[p, j] * _form(r, C, 6 * i, 6 * j)
            if aligned:
                var -= 2.0 * si * _form(r, D, 0, 6 * i)
        out[p] = np.sqrt(max(var, 0.0))


def pose_sigma(
    shares: NDArray[np.float64],
    rows: NDArray[np.float64],
    covariance: NDArray[np.float64],
    alignment_map: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """sqrt(l C l^T) of every point (mm): ``shares`` (M, n), ``rows`` (M, 6), ``covariance`` (6n, 6n,
    symmetric), ``alignment_map`` (6, 6n) or None (kinematic alignment: nothing taken out)."""
    s = np.ascontiguousarray(shares, dtype=np.float64)
    r = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, 6)
    C = np.ascontiguousarray(covariance, dtype=np.float64)
    aligned = alignment_map is not None
    B = np.asarray(alignment_map if aligned else np.zeros((6, C.shape[0])), dtype=np.float64)
    D = np.ascontiguousarray(B @ C)
    E = np.ascontiguousarray(D @ B.T)
    out = np.empty(len(r), dtype=np.float64)
    _pose_variance(s, r, C, D, E, aligned, out)
    return out
