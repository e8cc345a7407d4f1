"""The numba kernel of the simulated world's surface noise (:func:`fakes.sim.world.value_noise`), kept apart
from the world's schema so that validating a cell config's ``world:`` section does not load numba."""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray


@nb.njit(cache=True, inline="always")
def _lattice_value(ix: np.int64, iy: np.int64, iz: np.int64, seed: np.uint64) -> float:
    """Uniform value of unit variance at a lattice point (splitmix64-style hash of its coordinates)."""
    h = seed * np.uint64(0x9E3779B97F4A7C15)
    h = (h ^ np.uint64(ix)) * np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(31)
    h = (h ^ np.uint64(iy)) * np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    h = (h ^ np.uint64(iz)) * np.uint64(0xD6E8FEB86659FD93)
    h ^= h >> np.uint64(31)
    u = float(h >> np.uint64(11)) / 9007199254740992.0  # 2^53
    return (u - 0.5) * 3.4641016151377544  # sqrt(12): unit variance


@nb.njit(cache=True)
def lattice_noise(p: NDArray[np.float64], inv_grain: float, seed: np.uint64) -> NDArray[np.float64]:
    """Trilinearly interpolated lattice values at the points ``p`` (N, 3) scaled by ``inv_grain`` (1/mm)."""
    out = np.empty(len(p))
    norm = 1.0 / np.sqrt((2.0 / 3.0) ** 3)  # trilinear blending of iid unit values leaves variance (2/3)^3
    for n in range(len(p)):
        x, y, z = p[n, 0] * inv_grain, p[n, 1] * inv_grain, p[n, 2] * inv_grain
        fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
        ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
        tx, ty, tz = x - fx, y - fy, z - fz
        acc = 0.0
        for c in range(8):
            dx, dy, dz = c & 1, (c >> 1) & 1, (c >> 2) & 1
            w = (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty) * (tz if dz else 1.0 - tz)
            acc += w * _lattice_value(ix + dx, iy + dy, iz + dz, seed)
        out[n] = acc * norm
    return out
