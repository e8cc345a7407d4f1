"""Merging of registered multi-view clouds: overlaps averaged on a voxel grid with per-point quality weights.

All views are already in one frame (the part frame {P}, mm). Every input point falls in one voxel of a grid of
side ``voxel_mm``; each occupied voxel yields one output point, the weighted mean of the points in it. With
weights w_i = 1 / sigma_i^2 (sigma_i: the point's expected noise, mm, e.g. from the sensing error model) the
mean is the minimum-variance estimate and its expected noise is 1 / sqrt(sum w_i) (``sigma_mm``). Voxels seen
by one view keep that view's points averaged alone, so nothing outside the overlaps is lost; ``source``
maps every input point to its output point.

Choose ``voxel_mm`` about the views' point spacing: much coarser voxels also average real surface shape.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from cell.errors import ConfigError


@dataclass(frozen=True)
class MergedCloud:
    """``points_mm`` (M, 3) weighted voxel means; ``weight`` (M,) summed weights; ``count`` (M,) input points
    per voxel; ``n_views`` (M,) distinct views per voxel; ``source`` (N,) output index of every finite input
    point in the concatenated input order (-1 for dropped non-finite points)."""

    points_mm: NDArray[np.float64]
    weight: NDArray[np.float64]
    count: NDArray[np.int64]
    n_views: NDArray[np.int64]
    source: NDArray[np.int64]

    @property
    def sigma_mm(self) -> NDArray[np.float64]:
        """Expected noise of each merged point when the weights are 1 / sigma^2 (mm)."""
        return 1.0 / np.sqrt(self.weight)


def voxel_keys(points: NDArray[np.float64], voxel_mm: float) -> NDArray[np.int64]:
    """One int64 per point naming its voxel of edge ``voxel_mm`` (mm): equal keys, same voxel. Voxels are
    fixed to the frame's origin; keys run row-major over this call's occupied box (so keys of two calls are
    not comparable: key all the points together), and one 1-D ``np.unique`` groups the points by voxel."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    cell = np.floor(points / voxel_mm).astype(np.int64)
    cell -= cell.min(0)
    dims = cell.max(0) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:
        raise ConfigError(f"{dims} voxels of {voxel_mm} mm overflow the voxel key; use larger voxels")
    return (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]


def voxel_subsample_index(points: NDArray[np.float64], voxel_mm: float) -> NDArray[np.int64]:
    """Indices (ascending) of one point, the first, per occupied voxel of edge ``voxel_mm`` (mm): an even
    thinning that keeps measured points as they are (no averaging, unlike :func:`merge_views`)."""
    _, first = np.unique(voxel_keys(points, voxel_mm), return_index=True)
    return np.sort(first)


def merge_views(
    views: Sequence[ArrayLike],
    weights: Sequence[ArrayLike] | None = None,
    voxel_mm: float = 0.2,
) -> MergedCloud:
    """Merge registered views ((N_k, 3) mm each) with per-point weights ((N_k,) > 0; default 1).

    Memory: besides the inputs, about 40 bytes a point (the voxel keys, one sort, the numbering); the views
    are never copied into one array (a 5 MP sensor's dozen views hold 30 million points)."""
    if not voxel_mm > 0:
        raise ConfigError(f"merge_views: voxel size must be > 0 mm, got {voxel_mm}")
    if len(views) == 0:
        raise ConfigError("merge_views: no views to merge")
    pts = [np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in views]
    if weights is not None and len(weights) != len(pts):
        raise ConfigError(f"merge_views: {len(pts)} views but {len(weights)} weight arrays")
    ws = [
        np.ones(len(p)) if weights is None else np.broadcast_to(np.asarray(w, dtype=np.float64), (len(p),))
        for p, w in zip(pts, weights if weights is not None else [None] * len(pts), strict=True)
    ]
    oks = [np.isfinite(p).all(1) & np.isfinite(w) & (w > 0) for p, w in zip(pts, ws, strict=True)]
    if not any(ok.any() for ok in oks):
        raise ConfigError("merge_views: no finite points with a positive weight in any view")
    pts = [p if ok.all() else p[ok] for p, ok in zip(pts, oks, strict=True)]
    ws = [w if ok.all() else w[ok] for w, ok in zip(ws, oks, strict=True)]
    view = np.repeat(np.arange(len(pts), dtype=np.int32), [len(p) for p in pts])
    inv, n_views = _voxels(_voxel_keys_of_views(pts, voxel_mm), view)
    del view
    m = len(n_views)
    wsum, sums, count = np.zeros(m), np.zeros((m, 3)), np.zeros(m, dtype=np.int64)
    start = 0
    for p, w in zip(pts, ws, strict=True):  # view by view: no concatenated copy of the points
        at = inv[start : start + len(p)]
        start += len(p)
        wsum += np.bincount(at, weights=w, minlength=m)
        for k in range(3):
            sums[:, k] += np.bincount(at, weights=w * p[:, k], minlength=m)
        count += np.bincount(at, minlength=m)
    source = np.full(sum(len(ok) for ok in oks), -1, np.int64)
    source[np.concatenate(oks)] = inv
    return MergedCloud(
        points_mm=sums / wsum[:, None], weight=wsum, count=count, n_views=n_views, source=source
    )


def _voxel_keys_of_views(pts: list[NDArray[np.float64]], voxel_mm: float) -> NDArray[np.int64]:
    """:func:`voxel_keys` of the views' points taken together, computed view by view (one int64 a point)."""
    cells = [(np.floor(p.min(0) / voxel_mm), np.floor(p.max(0) / voxel_mm)) for p in pts if len(p)]
    lo = np.min([c[0] for c in cells], axis=0).astype(np.int64)
    dims = np.max([c[1] for c in cells], axis=0).astype(np.int64) - lo + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:
        raise ConfigError(f"{dims} voxels of {voxel_mm} mm overflow the voxel key; use larger voxels")
    keys = np.empty(sum(len(p) for p in pts), dtype=np.int64)
    start = 0
    for p in pts:
        cell = np.floor(p / voxel_mm).astype(np.int64) - lo
        keys[start : start + len(p)] = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
        start += len(p)
    return keys


def _voxels(keys: NDArray[np.int64], view: NDArray[np.int32]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Each point's voxel number (voxels numbered by ascending key, as ``np.unique`` numbers them) and each
    voxel's count of distinct views, from one stable sort of the keys: within a voxel the points keep their
    input order, which is view by view, so a view starts where the view number changes."""
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.empty(len(keys), dtype=bool)
    starts[:1] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=starts[1:])
    del sorted_keys
    number = np.cumsum(starts)
    number -= 1
    sorted_view = view[order]
    new_view = starts  # a voxel's first point, or a point of another view than the one before it
    new_view[1:] |= sorted_view[1:] != sorted_view[:-1]
    del sorted_view
    n_views = np.bincount(number[new_view], minlength=int(number[-1]) + 1 if len(number) else 0)
    inv = np.empty(len(keys), dtype=np.int64)
    inv[order] = number
    return inv, n_views


def measured_elsewhere(points: ArrayLike, others: Sequence[ArrayLike], radius_mm: float) -> NDArray[np.bool_]:
    """Which of ``points`` ((N, 3) mm) have a point of ``others`` (views in the same frame) within
    ``radius_mm``: where a view that could not be registered against the rest is redundant. Such a view
    keeps its kinematic pose (off by up to the chain's error, tenths of a millimetre); merged where
    registered views measured the same surface, its points would sit beside theirs, a voxel apart, as a
    false deviation."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(p):
        return np.zeros(0, dtype=bool)
    lo, hi = p.min(0) - radius_mm, p.max(0) + radius_mm  # only points in this box can be that close
    rest = [np.asarray(o, dtype=np.float64).reshape(-1, 3) for o in others]
    rest = [o[np.all((o >= lo) & (o <= hi), axis=1)] for o in rest if len(o)]
    rest = [o for o in rest if len(o)]
    if not rest:
        return np.zeros(len(p), dtype=bool)
    d, _ = cKDTree(np.vstack(rest)).query(p, distance_upper_bound=radius_mm)
    return np.isfinite(d)


def cut_unregistered(
    points: list[NDArray[np.float64]],
    weights: list[NDArray[np.float64]],
    unregistered: Sequence[int],
    radius_mm: float,
    *per_point: list[NDArray[np.float64]],
) -> int:
    """Cut each unregistered view (index into ``points``/``weights`` and any further ``per_point`` lists of
    per-point arrays, changed in place) back to the surface that neither a registered view nor an earlier
    unregistered one measured (:func:`measured_elsewhere`); returns how many points were cut."""
    held = set(unregistered)
    others = [p for m, p in enumerate(points) if m not in held]
    cut = 0
    for k in sorted(held):
        redundant = measured_elsewhere(points[k], others, radius_mm)
        points[k], weights[k] = points[k][~redundant], weights[k][~redundant]
        for values in per_point:
            values[k] = values[k][~redundant]
        others.append(points[k])
        cut += int(redundant.sum())
    return cut
