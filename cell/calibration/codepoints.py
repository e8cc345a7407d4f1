"""Encoded points: where the camera sees a given projector coordinate (u, v), with sub-pixel precision.

Step 2 of the dissertation's 5.1.1: the intersection of a decoded horizontal and vertical stripe line. Here
the
decoded maps u(x, y) and v(x, y) are fitted by a plane over a small window around the pixel whose code is
nearest (a least-squares line fit in both directions at once) and the plane pair is solved for the sub-pixel
position where u = u_i and v = v_j.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage


def _seeds(u: NDArray, v: NDArray, codes: NDArray, shape_p: tuple[int, int]) -> NDArray[np.int64]:
    """Flat index of a camera pixel whose decoded (u, v) rounds to each code's projector pixel (-1: none)."""
    ok = np.isfinite(u) & np.isfinite(v)
    iu, iv = np.rint(u[ok]).astype(np.int64), np.rint(v[ok]).astype(np.int64)
    inside = (iu >= 0) & (iu < shape_p[1]) & (iv >= 0) & (iv < shape_p[0])
    table = np.zeros(shape_p, np.int64)  # pixel index + 1, 0 = none
    table[iv[inside], iu[inside]] = np.flatnonzero(ok)[inside] + 1
    for _ in range(3):  # projector pixels no camera pixel rounds to: borrow a neighbour's pixel
        grown = ndimage.grey_dilation(table, size=(3, 3))
        table = np.where(table == 0, grown, table)
    cu = np.clip(np.rint(codes[:, 0]).astype(np.int64), 0, shape_p[1] - 1)
    cv = np.clip(np.rint(codes[:, 1]).astype(np.int64), 0, shape_p[0] - 1)
    return table[cv, cu] - 1


def locate_codes(
    u: NDArray,
    v: NDArray,
    codes_uv: NDArray,
    projector_size: tuple[int, int],
    half_window: int = 2,
    min_samples: int = 9,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera position (x, y) px of every projector code (u_i, v_j) in ``codes_uv`` (N, 2), NaN where not
    seen,
    and the unit direction of grad u there (the stripe gradient, camera px frame), both (N, 2).

    ``u``, ``v``: decoded projector coordinate maps (H, W), NaN where invalid; ``projector_size`` (w, h)."""
    H, W = u.shape
    codes = np.asarray(codes_uv, dtype=np.float64)
    out = np.full((len(codes), 2), np.nan)
    grad = np.full((len(codes), 2), np.nan)
    seed = _seeds(u, v, codes, (projector_size[1], projector_size[0]))
    idx = np.flatnonzero(seed >= 0)
    y0, x0 = np.divmod(seed[idx], W)
    for _ in range(2):  # fit around the seed, then once more around the first solution
        off = np.arange(-half_window, half_window + 1)
        dy, dx = [a.ravel() for a in np.meshgrid(off, off, indexing="ij")]
        ys, xs = y0[:, None] + dy, x0[:, None] + dx
        inside = (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
        ys, xs = np.clip(ys, 0, H - 1), np.clip(xs, 0, W - 1)
        uu, vv = u[ys, xs].astype(np.float64), v[ys, xs].astype(np.float64)
        w = (inside & np.isfinite(uu) & np.isfinite(vv)).astype(np.float64)
        uu, vv = np.nan_to_num(uu), np.nan_to_num(vv)
        A = np.stack([np.ones_like(w), np.broadcast_to(dx, w.shape), np.broadcast_to(dy, w.shape)], -1)
        AtA = np.einsum("nk,nki,nkj->nij", w, A, A) + 1e-9 * np.eye(3)
        cu = np.linalg.solve(AtA, np.einsum("nk,nki,nk->ni", w, A, uu)[..., None])[..., 0]
        cv = np.linalg.solve(AtA, np.einsum("nk,nki,nk->ni", w, A, vv)[..., None])[..., 0]
        J = np.stack([cu[:, 1:], cv[:, 1:]], 1)  # d(u, v)/d(x, y)
        rhs = codes[idx] - np.stack([cu[:, 0], cv[:, 0]], -1)
        det = np.linalg.det(J)
        good = (w.sum(1) >= min_samples) & (np.abs(det) > 1e-6)
        step = np.linalg.solve(np.where(good[:, None, None], J, np.eye(2)), rhs[..., None])[..., 0]
        good &= np.all(np.abs(step) <= half_window + 0.5, axis=1)
        x = x0 + step[:, 0]
        y = y0 + step[:, 1]
        nx, ny = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
        moved = (nx != x0) | (ny != y0)
        x0, y0 = np.clip(nx, 0, W - 1), np.clip(ny, 0, H - 1)
        if not moved.any():
            break
    out[idx[good], 0], out[idx[good], 1] = x[good], y[good]
    g = cu[:, 1:] / np.maximum(np.linalg.norm(cu[:, 1:], axis=1, keepdims=True), 1e-12)
    grad[idx[good]] = g[good]
    return out, grad
