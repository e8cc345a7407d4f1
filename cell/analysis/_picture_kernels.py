"""Compiled kernel of the report's pictures (numba; loaded through :mod:`cell.analysis.kernels`): the depth
buffer. Written as a loop because numpy's unbuffered ``np.maximum.at`` / ``np.minimum.at`` pair that does the
same costs ~40 ns an entry (a quarter of the four views' CPU at 200k points) and no installed library draws
points by depth (OpenCV and Pillow have no z-buffer)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def zbuffer(pix, depth, n_pixels):
    """Per pixel (flat index into ``n_pixels``) the index of the nearest entry drawn there (largest finite
    ``depth``; of equally near ones the first; -1: none) and its depth (NaN: none)."""
    nearest = np.full(n_pixels, -np.inf)
    winner = np.full(n_pixels, -1, np.int64)
    for i in range(pix.shape[0]):
        p = pix[i]
        if depth[i] > nearest[p]:
            nearest[p] = depth[i]
            winner[p] = i
    out = np.empty(n_pixels)
    for p in range(n_pixels):
        out[p] = nearest[p] if winner[p] >= 0 else np.nan
    return winner, out
