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

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from cell.errors import ConfigError


@dataclass(frozen=True)
class MergedCloud:
    """``points_mm`` (M, 3) weighted voxel means; ``weight`` (M,) summed weights; ``count`` (M,) input points
    per voxel; ``n_views`` (M,) distinct views per voxel; ``source`` (N,) output index of every finite input
    point in the concatenated input order (-1 for dropped non-finite points; None from
    :func:`merge_view_stream`, which gives it view by view)."""

    points_mm: NDArray[np.float64]
    weight: NDArray[np.float64]
    count: NDArray[np.int64]
    n_views: NDArray[np.int64]
    source: NDArray[np.int64] | None

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


class VoxelGrid:
    """The merge's voxel numbering, built from views given one at a time: the occupied voxels of edge
    ``voxel_mm`` (mm) of all the views, numbered by ascending row-major key over their occupied box (as
    ``np.unique`` of :func:`voxel_keys` of all points taken together numbers them), and each voxel's count of
    distinct views. Row-major keys over any box that holds two voxels order them as their integer cells
    (x, then y, then z), so the voxels found so far keep their order when a view widens the box.

    Memory: the occupied voxels (8 bytes each, twice while a view is added) and one view's points' cells;
    never every view's points at once."""

    def __init__(self, voxel_mm: float) -> None:
        if not voxel_mm > 0:
            raise ConfigError(f"merge: voxel size must be > 0 mm, got {voxel_mm}")
        self.voxel_mm = voxel_mm
        self.lo = np.zeros(3, dtype=np.int64)  # the occupied box's lowest cell
        self.dims = np.zeros(3, dtype=np.int64)  # its cells along x, y, z (0: no voxel yet)
        self.keys = np.zeros(0, dtype=np.int64)  # (M,) the occupied voxels' keys in the box, ascending
        self.n_views = np.zeros(0, dtype=np.int64)  # (M,) distinct views per voxel

    def add_view(self, points: NDArray[np.float64]) -> None:
        """Add one view's (finite) points ((N, 3) mm) to the occupied voxels."""
        if not len(points):
            return
        cell = self._cells(points)
        lo, hi = cell.min(0), cell.max(0)
        if len(self.keys):
            lo, hi = np.minimum(lo, self.lo), np.maximum(hi, self.lo + self.dims - 1)
        dims = hi - lo + 1
        if float(np.prod(dims.astype(np.float64))) >= 2.0**62:
            raise ConfigError(
                f"{dims} voxels of {self.voxel_mm} mm overflow the voxel key; use larger voxels"
            )
        if not len(self.keys) or ((lo == self.lo).all() and (dims == self.dims).all()):
            held = self.keys
        else:  # the box widened: the same voxels' keys in the new one
            held = _encode(_decode(self.keys, self.dims) + (self.lo - lo), dims)
        new = np.sort(_encode(cell - lo, dims))  # np.unique (hashing, then sorting) took 5 times as long
        del cell
        new = new[np.concatenate([[True], new[1:] != new[:-1]])]
        keys = np.concatenate([held, new])
        count = np.concatenate([self.n_views, np.ones(len(new), dtype=np.int64)])
        del held, new
        order = np.argsort(keys, kind="stable")  # two ascending runs
        keys, count = keys[order], count[order]
        del order
        first = np.empty(len(keys), dtype=bool)
        first[:1] = True
        np.not_equal(keys[1:], keys[:-1], out=first[1:])
        self.n_views = np.add.reduceat(count, np.flatnonzero(first)) if len(keys) else count
        self.keys, self.lo, self.dims = keys[first], lo, dims

    def number(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """The voxel number of each of ``points`` ((N, 3) mm, finite, inside voxels added before)."""
        return np.searchsorted(self.keys, _encode(self._cells(points) - self.lo, self.dims)).astype(np.int64)

    def _cells(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        return np.floor(points / self.voxel_mm).astype(np.int64)


def _encode(cell: NDArray[np.int64], dims: NDArray[np.int64]) -> NDArray[np.int64]:
    """Row-major keys of cells (N, 3) in a box of ``dims`` cells whose lowest cell is 0."""
    return (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]


def _decode(keys: NDArray[np.int64], dims: NDArray[np.int64]) -> NDArray[np.int64]:
    """The cells (N, 3) of row-major keys in a box of ``dims`` cells (:func:`_encode`'s inverse)."""
    yz = keys % (dims[1] * dims[2])
    return np.column_stack([keys // (dims[1] * dims[2]), yz // dims[2], yz % dims[2]])


def merge_view_stream(
    views: Callable[[], Iterable[tuple[NDArray[Any], ...]]],
    voxel_mm: float = 0.2,
    each_view: Callable[[int, NDArray[np.int64], int, NDArray[np.float64], tuple[NDArray[Any], ...]], None]
    | None = None,
) -> MergedCloud | None:
    """Merge registered views read one at a time, as :func:`merge_views` merges them (the same voxels, sums
    and order: the same bits), without holding more than one view's points.

    ``views()`` yields each view's (points (N_k, 3) mm, weights (N_k,) > 0, *per_point arrays (N_k, ...)) in
    view order; it is called twice (the voxels first, then the sums), and must yield the same both times.
    ``each_view(k, number, m, weights, per_point)``, when given, is called on the second pass with view k's
    finite points' voxel numbers (of the ``m`` merged points), weights and per-point arrays (the finite
    points'), e.g. to accumulate each view's share of the merged points. The result's ``source`` is None:
    ``number`` is each view's part of it. None when no view has a finite point with a positive weight."""
    grid = VoxelGrid(voxel_mm)
    n_total = 0
    for p, w, *_ in views():
        p, w = _finite(p, w)[:2]
        grid.add_view(p)
        n_total += len(p)
    if not n_total:
        return None
    m = len(grid.keys)
    wsum, sums, count = np.zeros(m), np.zeros((m, 3)), np.zeros(m, dtype=np.int64)
    for k, (p, w, *per_point) in enumerate(views()):
        p, w, ok = _finite(p, w)
        at = grid.number(p)
        wsum += np.bincount(at, weights=w, minlength=m)
        for j in range(3):
            sums[:, j] += np.bincount(at, weights=w * p[:, j], minlength=m)
        count += np.bincount(at, minlength=m)
        if each_view is not None:
            each_view(k, at, m, w, tuple(x if ok is None else x[ok] for x in per_point))
    return MergedCloud(
        points_mm=sums / wsum[:, None], weight=wsum, count=count, n_views=grid.n_views, source=None
    )


def _finite(
    p: NDArray[np.float64], w: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
    """A view's points with a finite position and a finite, positive weight, and which (None: all)."""
    ok = np.isfinite(p).all(1) & np.isfinite(w) & (w > 0)
    return (p, w, None) if ok.all() else (p[ok], w[ok], ok)


def merge_views(
    views: Sequence[ArrayLike],
    weights: Sequence[ArrayLike] | None = None,
    voxel_mm: float = 0.2,
) -> MergedCloud:
    """Merge registered views ((N_k, 3) mm each) with per-point weights ((N_k,) > 0; default 1), given in
    memory (:func:`merge_view_stream` reads them one at a time); ``source`` maps every input point.

    Memory: besides the inputs, the occupied voxels and 8 bytes a point (``source``); the views are never
    copied into one array (a 5 MP sensor's dozen views hold 30 million points)."""
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
    source = np.full(sum(len(p) for p in pts), -1, np.int64)
    starts = np.cumsum([0] + [len(p) for p in pts])

    def each_view(
        k: int, number: NDArray[np.int64], m: int, w: NDArray[np.float64], index: tuple[NDArray[Any], ...]
    ) -> None:
        source[starts[k] + index[0]] = number  # the view's finite points

    merged = merge_view_stream(
        lambda: ((p, w, np.arange(len(p))) for p, w in zip(pts, ws, strict=True)), voxel_mm, each_view
    )
    if merged is None:
        raise ConfigError("merge_views: no finite points with a positive weight in any view")
    return MergedCloud(merged.points_mm, merged.weight, merged.count, merged.n_views, source)


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


def unregistered_redundant(
    points: Callable[[int], NDArray[np.float64]], n_views: int, unregistered: Sequence[int], radius_mm: float
) -> dict[int, NDArray[np.bool_]]:
    """Which points of each unregistered view (an index of the ``n_views`` views, whose points ``points(k)``
    gives, (N_k, 3) mm) a registered view or an earlier unregistered one (cut so) measured
    (:func:`measured_elsewhere`). The views are read one at a time: the unregistered ones are held, and of the
    registered ones only their points within ``radius_mm`` of the unregistered views' box."""
    held = sorted(set(unregistered))
    if not held:
        return {}
    mine = {k: np.asarray(points(k), dtype=np.float64).reshape(-1, 3) for k in held}
    boxes = [(p.min(0) - radius_mm, p.max(0) + radius_mm) for p in mine.values() if len(p)]
    others: list[NDArray[np.float64]] = []
    if boxes:  # measured_elsewhere looks no further than a view's own box, which this one holds
        lo, hi = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
        for m in range(n_views):
            if m not in mine:
                o = np.asarray(points(m), dtype=np.float64).reshape(-1, 3)
                others.append(o[np.all((o >= lo) & (o <= hi), axis=1)])
    redundant = {}
    for k in held:
        redundant[k] = measured_elsewhere(mine[k], others, radius_mm)
        others.append(mine[k][~redundant[k]])
    return redundant


def cut_unregistered(
    points: list[NDArray[np.float64]],
    weights: list[NDArray[np.float64]],
    unregistered: Sequence[int],
    radius_mm: float,
    *per_point: list[NDArray[np.float64]],
) -> int:
    """Cut each unregistered view (index into ``points``/``weights`` and any further ``per_point`` lists of
    per-point arrays, changed in place) back to the surface that neither a registered view nor an earlier
    unregistered one measured (:func:`unregistered_redundant`); returns how many points were cut."""
    redundant = unregistered_redundant(lambda k: points[k], len(points), unregistered, radius_mm)
    for k, cut in redundant.items():
        points[k], weights[k] = points[k][~cut], weights[k][~cut]
        for values in per_point:
            values[k] = values[k][~cut]
    return int(sum(int(cut.sum()) for cut in redundant.values()))
