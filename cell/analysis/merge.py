"""Merging of registered multi-view clouds: overlaps averaged on a voxel grid with per-point quality weights.

Every point falls in one voxel of a grid of side ``voxel_mm`` in the part frame {P} (mm); each occupied voxel
yields one output point, the weighted mean of the points in it. With weights w_i = 1 / sigma_i^2 (sigma_i:
the point's expected noise, mm, e.g. from the sensing error model) the mean is the minimum-variance estimate
and its expected noise is 1 / sqrt(sum w_i) (``sigma_mm``). Voxels seen by one view keep that view's points
averaged alone, so nothing outside the overlaps is lost.

The work is split at the views' refinement (issue 16). As a view arrives its points are binned once at their
kinematic positions (T_P_W @ p_W; :func:`bin_view`: per voxel the view's weight sum W_b and weighted mean
m_b). After the last view each bin's mean is moved by its view's refinement T_v = [R_v t_v] and merged in the
voxel it then falls in (:func:`merge_bins`): sum W_b (R_v m_b + t_v) / sum W_b, which is the weighted mean of
the refined points, as exactly as a bin's points are moved together. Against binning every refined point that
changes the model in three ways: (a) a bin's points move together (1.04 points a bin of 0.2 mm on the demo
pillar's 1024x768 views, 1.02-1.09 per view, `bench/hash_register.py`; ~4 on a 5 MP camera's,
docs/benchmarks.md: the demo pillar merges to 1.6 % fewer points, deviations within 2.3 um at p99); (b) a view
the refinement could not register is cut by whole voxels, judged by their means (:func:`held_redundant`), not
point by point; (c) the registered cloud's u takes its surface normals from the faces of the aligned cloud's
error map (one nearest face a merged point; cell.inspection_results).

Choose ``voxel_mm`` about the views' point spacing: much coarser voxels also average real surface shape.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from cell.errors import ConfigError
from cell.geometry import bounding_box, invert, transform_points

KEY_BITS = 21  # bits per axis of a voxel key: +-2^20 voxels (+-210 m of 0.2 mm voxels) about the origin
_HALF = 1 << (KEY_BITS - 1)


@dataclass(frozen=True)
class MergedCloud:
    """``points_mm`` (M, 3) weighted voxel means; ``weight`` (M,) summed weights; ``count`` (M,) input points
    per voxel; ``n_views`` (M,) distinct views per voxel."""

    points_mm: NDArray[np.float64]
    weight: NDArray[np.float64]
    count: NDArray[np.int64]
    n_views: NDArray[np.int64]

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
    thinning that keeps measured points as they are (no averaging, unlike the merge)."""
    _, first = np.unique(voxel_keys(points, voxel_mm), return_index=True)
    return np.sort(first)


def grid_keys(cells: NDArray[np.int64]) -> NDArray[np.int64]:
    """One int64 per voxel cell (N, 3) of the merge grid, the same in every call (unlike :func:`voxel_keys`):
    ordered as the cells (x, then y, then z)."""
    if len(cells) and (cells.min() < -_HALF or cells.max() >= _HALF):
        raise ConfigError(f"merge: points beyond +-{_HALF} voxels of the part frame's origin")
    c = cells + _HALF
    return np.asarray((c[:, 0] << (2 * KEY_BITS)) | (c[:, 1] << KEY_BITS) | c[:, 2], dtype=np.int64)


@dataclass(frozen=True)
class ViewBins:
    """One view's points binned on the merge grid at their kinematic positions in {P}: per occupied voxel (in
    the order of its keys, :func:`bin_view`) the points' weighted ``mean`` (mm), weight sum ``weight``,
    weighted sum of their decode u ``wu`` (mm; NaN where a point has none) and ``count``. They depend on the
    view alone. 40 bytes a voxel (a 1024x768 pillar view's points fall 1.02-1.09 to a voxel of 0.2 mm)."""

    mean: NDArray[np.float64]
    weight: NDArray[np.float64]
    wu: NDArray[np.float32]
    count: NDArray[np.int32]

    @property
    def nbytes(self) -> int:
        return int(sum(x.nbytes for x in (self.mean, self.weight, self.wu, self.count)))

    def __len__(self) -> int:
        return len(self.weight)


def bin_view(
    points: NDArray[np.float64], weights: NDArray[np.float64], u: NDArray[np.float64] | None, voxel_mm: float
) -> ViewBins:
    """Bin one view's points ((N, 3) mm in {P}, at the pose the kinematic chain gave them) with their merge
    weights ((N,) > 0) and decode u ((N,) mm, or None) on the merge grid of edge ``voxel_mm`` (mm): its
    :class:`ViewBins`, in the order of the voxels' keys (:func:`grid_keys`). Points with a non-finite position
    or a weight that is not finite and positive are left out."""
    if not voxel_mm > 0:
        raise ConfigError(f"merge: voxel size must be > 0 mm, got {voxel_mm}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64).ravel()
    ok = np.isfinite(p).all(1) & np.isfinite(w) & (w > 0)
    if not ok.all():
        p, w = p[ok], w[ok]
        u = None if u is None else np.asarray(u)[ok]
    keys = grid_keys(np.floor(p / voxel_mm).astype(np.int64))
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    first = np.empty(len(keys), dtype=bool)
    first[:1] = True
    np.not_equal(keys[1:], keys[:-1], out=first[1:])
    at = np.cumsum(first) - 1
    n = int(at[-1]) + 1 if len(at) else 0
    w = w[order]
    wsum = np.asarray(np.bincount(at, weights=w, minlength=n), dtype=np.float64)
    mean = np.empty((n, 3))
    for j in range(3):
        mean[:, j] = np.bincount(at, weights=w * p[order, j], minlength=n) / wsum
    if u is None:
        wu = np.full(n, np.nan)
    else:
        wu = np.bincount(at, weights=w * np.asarray(u, dtype=np.float64).ravel()[order], minlength=n)
    count = np.bincount(at, minlength=n).astype(np.int32)
    return ViewBins(mean, wsum, wu.astype(np.float32), count)


def merge_bins(
    voxel_mm: float,
    views: Callable[[int], ViewBins],
    keep: Sequence[NDArray[np.bool_] | None],
    T: Sequence[NDArray[np.float64]],
    each_view: EachView | None = None,
) -> MergedCloud | None:
    """Merge binned views: ``views(k)`` gives view k's bins (:func:`bin_view` on the grid of edge
    ``voxel_mm``, mm; asked for twice, in view order); ``T[k]`` is its refinement (4x4, {P} to {P}) and
    ``keep[k]`` which of its bins it gives (None: all; a view the refinement could not register gives only
    what no other view measured: :func:`held_redundant`).

    Each bin's mean, moved by its view's refinement, falls in a voxel of the grid (most in the one it was
    binned in: the refinement's corrections are tens of um); each occupied voxel's point is sum W_b (R_v m_b +
    t_v) / sum W_b over the bins in it (m_b a bin's mean at the kinematic pose, W_b its weight sum), summed in
    view order. That is the weighted mean of the refined points in the voxel, binned at their refined
    positions as a bin's points go together (a bin of a 0.2 mm grid holds ~1.04 of a 1024x768 view's points;
    merging the bins where they were binned, at the kinematic positions, would leave two views' surfaces,
    apart by the chain's error, in two layers of voxels averaged apart: on the demo pillar 7 % more points and
    a noisier cloud). The voxels come in the order of their keys (x, then y, then z): the result depends on
    the views' bins alone (not on when they were binned). Two passes over the views, compiled
    (cell.analysis._merge_kernel): the first finds the voxels the moved bins fall into, the second adds the
    sums; only those voxels are held (in bricks of 1 x 8 x 8, ~7 voxels a brick on the demo pillar: 16 bytes a
    brick in a hash at most 3/4 full, then 48 bytes a brick in the order of their keys).

    ``each_view(k, rows, m, weight, wu)``, when given, is called with the merged points view k has (``rows``
    of the ``m``, ascending, int32), its weight sums there and its weighted u sums, e.g. for the views' shares
    (:class:`cell.analysis.uncertainty.MergeShares`). None when no view gives a voxel. The same merge can be
    made in two parts, all views but the last before the last is known (:func:`merge_bins_ahead`, then
    :meth:`PartialMerge.finish`), to the bit."""
    bricks, m, n_most = _first_pass(voxel_mm, views, keep, T)
    if not m:
        return None
    wsum, sums = np.zeros(m), np.zeros((m, 3))
    count, n_views = np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.int64)
    add = _Adder(bricks, voxel_mm, wsum, sums, count, n_views, n_most)
    for k, (kept, T_k) in enumerate(zip(keep, T, strict=True)):
        rows, w_rows, wu_rows = add(views(k), kept, T_k)
        if each_view is not None:
            each_view(k, rows, m, w_rows, wu_rows)
    return MergedCloud(np.divide(sums, wsum[:, None], out=sums), wsum, count, n_views)


# ``each_view`` of :func:`merge_bins`: (view k, its merged points' rows, how many merged points, its weight
# sums and weighted u sums there)
EachView = Callable[[int, NDArray[Any], int, NDArray[np.float64], NDArray[np.float64]], None]
_EVERY = np.zeros(0, dtype=bool)  # (the kernels' "all kept")


def _first_pass(
    voxel_mm: float,
    views: Callable[[int], ViewBins],
    keep: Sequence[NDArray[np.bool_] | None],
    T: Sequence[NDArray[np.float64]],
) -> tuple[NDArray[np.int64], int, int]:
    """The merge's first pass over all the views (:func:`merge_bins`'s arguments): the bricks of the voxels
    the moved bins fall in (a hash of their keys and occupied voxels, the kernel's), numbered in the order of
    their keys for the second pass; how many voxels; the most bins of a view (the second pass's scratch)."""
    if not voxel_mm > 0:
        raise ConfigError(f"merge: voxel size must be > 0 mm, got {voxel_mm}")
    table = np.full((1024, 2), -1, dtype=np.int64)
    n_bricks, n_most = 0, 0
    for k, (kept, T_k) in enumerate(zip(keep, T, strict=True)):
        b = views(k)
        n_most = max(n_most, len(b))
        table, n_bricks = _mark(table, n_bricks, k, b, kept, T_k, voxel_mm)
    bricks, m = _numbered(table)
    return bricks, m, n_most


def _mark(
    table: NDArray[np.int64],
    n_bricks: int,
    k: int,
    b: ViewBins,
    kept: NDArray[np.bool_] | None,
    T_k: NDArray[np.float64],
    voxel_mm: float,
) -> tuple[NDArray[np.int64], int]:
    """The merge's first pass over view ``k`` (its bins ``b``, those ``kept``, moved by ``T_k``): the voxels
    they fall in marked in the hash ``table`` of ``n_bricks`` bricks (grown, a new array, when 3/4 full)."""
    from cell.analysis import _merge_kernel as kernel

    if kept is not None and len(kept) != len(b):  # (the kernels do not check their indices)
        raise ValueError(f"merge: view {k}'s mask has {len(kept)} entries for its {len(b)} bins")
    given = _EVERY if kept is None else kept
    T_k = np.asarray(T_k, dtype=np.float64)
    at, status = 0, kernel.FULL
    while status == kernel.FULL:
        n_bricks, at, status = kernel.insert(table, n_bricks, b.mean, T_k, given, voxel_mm, at)
        if status == kernel.FULL:  # twice as large
            larger = np.full((2 * len(table), 2), -1, dtype=np.int64)
            kernel.rehash(table, larger)
            table = larger
    if status == kernel.OUT_OF_RANGE:
        raise ConfigError(
            f"merge: view {k}'s refined points are not finite or beyond +-{_HALF} voxels of the part "
            "frame's origin"
        )
    return table, n_bricks


def _numbered(table: NDArray[np.int64]) -> tuple[NDArray[np.int64], int]:
    """The second pass's bricks (in the order of their keys, their voxels numbered so) from the first pass's
    hash, and how many voxels."""
    return _numbered_entries(table, _by_key(table))


def _by_key(table: NDArray[np.int64]) -> NDArray[np.int64]:
    """The hash's occupied entries in the order of their keys."""
    slots = np.flatnonzero(table[:, 0] >= 0)
    return slots[np.argsort(table[slots, 0])]


def _numbered_entries(table: NDArray[np.int64], by_key: NDArray[np.int64]) -> tuple[NDArray[np.int64], int]:
    """The second pass's bricks of the hash ``table``'s entries ``by_key`` (in the order of their keys), and
    how many voxels."""
    from cell.analysis import _merge_kernel as kernel

    bricks = np.empty((len(by_key), kernel.BRICK_WORDS), dtype=np.int64)
    m = kernel.number(table, by_key, bricks)
    if m >= 2**31:
        raise ConfigError("merge: more than 2^31 voxels; use larger voxels")
    return bricks, m


class _Adder:
    """The merge's second pass, a view a call: its bins' sums added to the merged voxels' ``wsum``,
    ``sums``, ``count`` and ``n_views`` (numbered in ``bricks``), with the kernel's scratch for views of up
    to ``n_most`` bins. Returns the view's merged points (ascending, int32), its weight sums and weighted u
    sums there."""

    def __init__(
        self,
        bricks: NDArray[np.int64],
        voxel_mm: float,
        wsum: NDArray[np.float64],
        sums: NDArray[np.float64],
        count: NDArray[np.int64],
        n_views: NDArray[np.int64],
        n_most: int,
    ) -> None:
        m = len(wsum)
        self.bricks, self.voxel_mm = bricks, voxel_mm
        self.wsum, self.sums, self.count, self.n_views = wsum, sums, count, n_views
        # the kernel's scratch: a merged point's place among a view's, which the view has, its bins and sums
        self.local, self.seen = np.full(m, -1, dtype=np.int32), np.zeros((m + 63) // 64, dtype=np.uint64)
        self.many = np.empty(n_most, dtype=np.int32)
        self.first, self.rest = np.empty((n_most, 5)), np.empty((n_most, 5))

    def __call__(
        self, b: ViewBins, kept: NDArray[np.bool_] | None, T_k: NDArray[np.float64]
    ) -> tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.float64]]:
        from cell.analysis import _merge_kernel as kernel

        rows, w_rows, wu_rows = kernel.add_view(
            self.bricks,
            b.mean,
            np.asarray(T_k, dtype=np.float64),
            _EVERY if kept is None else kept,
            self.voxel_mm,
            b.weight,
            b.count,
            b.wu,
            self.wsum,
            self.sums,
            self.count,
            self.n_views,
            self.local,
            self.seen,
            self.many,
            self.first,
            self.rest,
        )
        return rows, w_rows, wu_rows


@dataclass
class PartialMerge:
    """:func:`merge_bins` of all views but the last, to be finished with the last (:meth:`finish`): the
    views' voxels (the second pass's bricks, numbered among themselves), the sums added so far and each
    view's ``each_view`` arguments (in that numbering). Made by :func:`merge_bins_ahead`; used once. 48
    bytes a voxel and 20 a view's voxel, besides 48 a brick (181-188 MB for the demo pillar's first 11 views:
    2.1M voxels of 3.8M bins)."""

    voxel_mm: float
    n_views_before: int  # the views merged (0 .. n_views_before - 1)
    bricks: NDArray[np.int64]  # the second pass's bricks of these views' voxels, in the order of their keys
    wsum: NDArray[np.float64]  # (m,) per voxel, as merge_bins has them after these views
    sums: NDArray[np.float64]  # (m, 3)
    count: NDArray[np.int64]
    n_views: NDArray[np.int64]
    # each view's each_view arguments: its merged points' rows (these views' numbering), weight and wu sums
    shares: list[tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.float64]]]
    used: bool = False

    @property
    def nbytes(self) -> int:
        """The bytes it holds."""
        arrays: list[NDArray[Any]] = [self.bricks, self.wsum, self.sums, self.count, self.n_views]
        arrays += [x for view in self.shares for x in view]
        return int(sum(x.nbytes for x in arrays))

    def finish(
        self,
        last: ViewBins,
        kept: NDArray[np.bool_] | None,
        T_last: NDArray[np.float64],
        each_view: EachView | None = None,
    ) -> MergedCloud | None:
        """:func:`merge_bins` of the views merged ahead and ``last`` (its bins, those ``kept``, moved by
        ``T_last``) to the bit, with its ``each_view`` calls, all views' in view order. Its first pass finds
        the last view's voxels (in a hash of its own), which are united with the earlier ones' (both in the
        order of their keys); the voxels are numbered again (in the order of their keys, as before: an
        earlier voxel's new number is a monotone map of its old one, so the views' rows stay ascending), the
        sums made ahead are moved to their voxels' new numbers and the last view's are added, last as in
        the full merge. Takes this partial's arrays (it can be finished once)."""
        from cell.analysis import _merge_kernel as kernel

        if self.used:
            raise RuntimeError("merge: a partial merge is finished once")
        self.used = True
        table = np.full((1024, 2), -1, dtype=np.int64)
        table, _ = _mark(table, 0, self.n_views_before, last, kept, T_last, self.voxel_mm)
        by_key = _by_key(table)
        both = np.empty((len(self.bricks) + len(by_key), 2), dtype=np.int64)
        n = kernel.united(self.bricks, table, by_key, both)
        del table, by_key
        bricks, m = _numbered_entries(both, np.arange(n))
        del both
        if not m:
            return None
        m_old = len(self.wsum)
        if m == m_old:  # no new voxel: the same numbering
            wsum, sums, count, n_views = self.wsum, self.sums, self.count, self.n_views
        else:
            moved = np.empty(m_old, dtype=np.int32)  # an earlier voxel's new number
            kernel.renumber(self.bricks, bricks, moved)
            wsum, sums = np.empty(m), np.empty((m, 3))
            count, n_views = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
            kernel.spread(moved, self.wsum, self.sums, self.count, self.n_views, wsum, sums, count, n_views)
            for rows_k, _, _ in self.shares:
                kernel.remap(moved, rows_k)
            del moved
            # the sums made ahead are in the new arrays now: not held beside them (~100 MB on the demo)
            self.wsum, self.sums = np.zeros(0), np.zeros((0, 3))
            self.count, self.n_views = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        self.bricks = bricks  # (the earlier voxels' bricks are not needed past the numbering)
        del bricks
        add = _Adder(self.bricks, self.voxel_mm, wsum, sums, count, n_views, len(last))
        rows, w_rows, wu_rows = add(last, kept, T_last)
        del add
        if each_view is not None:
            for k, (rows_k, w_k, wu_k) in enumerate(self.shares):
                each_view(k, rows_k, m, w_k, wu_k)
            each_view(self.n_views_before, rows, m, w_rows, wu_rows)
        self.shares = []
        return MergedCloud(np.divide(sums, wsum[:, None], out=sums), wsum, count, n_views)


def merge_bins_ahead(
    voxel_mm: float,
    views: Callable[[int], ViewBins],
    keep: Sequence[NDArray[np.bool_] | None],
    T: Sequence[NDArray[np.float64]],
) -> PartialMerge:
    """:func:`merge_bins` of views 0 .. len(T) - 1 (``views``, ``keep``, ``T`` as there), made before the
    view that follows them is known, to be finished with it (:meth:`PartialMerge.finish`): both passes over
    these views, their ``each_view`` arguments kept."""
    bricks, m, n_most = _first_pass(voxel_mm, views, keep, T)
    wsum, sums = np.zeros(m), np.zeros((m, 3))
    count, n_views = np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.int64)
    shares = []
    add = _Adder(bricks, voxel_mm, wsum, sums, count, n_views, n_most)
    for k, (kept, T_k) in enumerate(zip(keep, T, strict=True)):
        shares.append(add(views(k), kept, T_k))
    return PartialMerge(voxel_mm, len(T), bricks, wsum, sums, count, n_views, shares)


@functools.cache
def load_kernels() -> None:
    """Load the merge's compiled kernels (cell.analysis._merge_kernel; numba compiles them the first time and
    caches them), once a process: ~0.25 s CPU, which the first merge would otherwise spend after the last
    frame (the decode worker loads them as the first view arrives)."""
    from cell.analysis import _merge_kernel as kernel

    bins = bin_view(np.zeros((1, 3)), np.ones(1), np.zeros(1), 1.0)
    merge_bins(1.0, lambda k: bins, [np.ones(1, dtype=bool)], [np.eye(4)])
    # (a merge made ahead, finished with a view of a new voxel: the renumbering's kernel)
    merge_bins_ahead(1.0, lambda k: bins, [None], [np.eye(4)]).finish(
        bin_view(np.ones((1, 3)), np.ones(1), None, 1.0), None, np.eye(4)
    )
    kernel.rehash(np.full((2, 2), -1, dtype=np.int64), np.full((4, 2), -1, dtype=np.int64))
    kernel.add_squares(np.zeros(1), np.zeros(1, dtype=np.int32), np.zeros(1))


def moved_means(bins: ViewBins, T: NDArray[np.float64]) -> NDArray[np.float64]:
    """A view's voxel means (its points' weighted mean in each of its voxels, at the kinematic pose) moved by
    its refinement ``T`` (4x4, {P} to {P}), mm."""
    return transform_points(np.asarray(T, dtype=np.float64), bins.mean)


def measured_elsewhere(
    points: ArrayLike,
    others: Sequence[ArrayLike],
    radius_mm: float,
    around: _Around | None = None,
    near: Sequence[NDArray[np.float64]] = (),
) -> NDArray[np.bool_]:
    """Which of ``points`` ((N, 3) mm) have a point of ``others`` (views in the same frame) within
    ``radius_mm``: where a view that could not be registered against the rest is redundant. Such a view
    keeps its kinematic pose (off by up to the chain's error, tenths of a millimetre); merged where
    registered views measured the same surface, its points would sit beside theirs, a voxel apart, as a
    false deviation. ``around``: the points' :class:`_Around` when the caller made it already; ``near``: more
    others, (K, 3) mm each, selected by it already (:meth:`_Around.select`, which gives the same points
    again: not done twice), after ``others``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(p):
        return np.zeros(0, dtype=bool)
    around = _Around(p, radius_mm) if around is None else around
    rest = [around.select(np.asarray(o, dtype=np.float64).reshape(-1, 3)) for o in others]
    rest = [o for o in [*rest, *near] if len(o)]
    if not rest:
        return np.zeros(len(p), dtype=bool)
    d, _ = cKDTree(np.vstack(rest)).query(p, distance_upper_bound=radius_mm)
    return np.isfinite(d)


class _Around:
    """Where points of others can be within ``radius_mm`` of ``points`` ((N, 3) mm, N > 0): in their box grown
    by the radius, and in the cells of side radius_mm next to a cell of theirs (a view of few points spread
    over a wide box has far fewer others near it than in its box: the tree is built on those alone)."""

    def __init__(self, points: NDArray[np.float64], radius_mm: float) -> None:
        lo, hi = bounding_box(points)
        self.lo, self.hi = lo - radius_mm, hi + radius_mm
        self.radius_mm = radius_mm
        # (the distinct cells first, ~100 times fewer than a view's voxel means at 2 mm, then the neighbours)
        cells = np.unique(np.floor((points - self.lo) / radius_mm).astype(np.int64), axis=0)
        self.keys = np.unique(grid_keys((cells[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3)))

    def select(self, others: NDArray[np.float64]) -> NDArray[np.float64]:
        """The points of ``others`` ((K, 3) mm) in the box and the cells, in their order."""
        o = others[_in_box(others, self.lo, self.hi)]
        keys = grid_keys(np.floor((o - self.lo) / self.radius_mm).astype(np.int64))
        at = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return o[self.keys[at] == keys]


_NEIGHBOURS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)


def held_redundant(
    bins: Callable[[int], ViewBins],
    T: Sequence[NDArray[np.float64]],
    unregistered: Sequence[int],
    radius_mm: float,
) -> dict[int, NDArray[np.bool_]]:
    """Which voxels of each unregistered view (an index of the views whose bins ``bins(k)`` gives, refined by
    ``T[k]``, :func:`moved_means`) a registered view or an earlier unregistered one (cut so) measured: a
    voxel mean of theirs within ``radius_mm`` (:func:`measured_elsewhere`). The voxel means stand for the
    points in them (which lie within a voxel's diagonal, 0.35 mm at 0.2 mm, of their mean): a view's voxel
    is given or cut whole. Of the registered views only the voxels in the unregistered ones' box are moved,
    and each registered view's bins are asked for once. The same cut can be made in two parts
    (:class:`HeldCut`)."""
    return HeldCut(bins, T, unregistered, radius_mm).redundant


class HeldCut:
    """:func:`held_redundant` of the views ``bins``, ``T``, ``unregistered`` (as there), which can be made
    before the view that follows them is known and finished with it (:meth:`with_last`): it keeps the held
    views' moved voxel means and where others can be near them."""

    def __init__(
        self,
        bins: Callable[[int], ViewBins],
        T: Sequence[NDArray[np.float64]],
        unregistered: Sequence[int],
        radius_mm: float,
    ) -> None:
        self.radius_mm = radius_mm
        self.T = [np.array(T_k, dtype=np.float64) for T_k in T]
        self.held = sorted(set(unregistered))
        self.mine = {k: moved_means(bins(k), T[k]) for k in self.held}
        self.around = {k: _Around(p, radius_mm) for k, p in self.mine.items() if len(p)}
        # the registered views' moved voxel means near each held view (only points in its box and cells can
        # be that close: :class:`_Around`), each registered view's bins asked for once for all the held views
        near: dict[int, list[NDArray[np.float64]]] = {k: [] for k in self.around}
        for m in range(len(T)):
            if m in self.mine or not self.around:
                continue
            mean = bins(m).mean
            for k, a in self.around.items():
                near[k].append(_near(a, mean, self.T[m]))
        self.redundant: dict[int, NDArray[np.bool_]] = {}
        for k in self.held:
            if k not in self.around:
                self.redundant[k] = np.zeros(0, dtype=bool)
                continue
            others = [self.mine[j][~self.redundant[j]] for j in self.held if j in self.redundant]
            mine, around = self.mine[k], self.around[k]
            self.redundant[k] = measured_elsewhere(mine, others, radius_mm, around, near.pop(k))

    @property
    def nbytes(self) -> int:
        """The bytes of the held views' arrays it keeps (their moved means and cuts)."""
        return int(sum(p.nbytes for p in self.mine.values()) + sum(r.nbytes for r in self.redundant.values()))

    def with_last(
        self, bins: Callable[[int], ViewBins], T: Sequence[NDArray[np.float64]], unregistered: Sequence[int]
    ) -> dict[int, NDArray[np.bool_]]:
        """:func:`held_redundant` of these views and one more, the last (``bins``, ``T``, ``unregistered`` of
        all; these views' ``T`` and which of them are unregistered as made): the cut made, to the bit. The
        held views are cut in the order of their indices, so a held last view leaves the earlier ones' cuts
        as they are and is cut against them (their kept voxels) and the registered views. A registered last
        view can cut an earlier held one (and so change what the later held ones are cut against): where it
        comes near one (within its box and cells, :class:`_Around`) the cut is made again in full;
        elsewhere each held view is cut against the same points as before, so as before."""
        last = len(self.T)
        held = set(unregistered)
        if (
            len(T) != last + 1
            or sorted(k for k in held if k < last) != self.held
            or any(np.asarray(a).tobytes() != b.tobytes() for a, b in zip(T[:last], self.T, strict=False))
        ):
            return held_redundant(bins, T, unregistered, self.radius_mm)
        redundant = dict(self.redundant)
        T_last = np.asarray(T[last], dtype=np.float64)
        if last not in held:
            if self.around:
                mean = bins(last).mean
                if any(len(_near(a, mean, T_last)) for a in self.around.values()):
                    return held_redundant(bins, T, unregistered, self.radius_mm)
            return redundant
        p = moved_means(bins(last), T_last)
        if not len(p):
            redundant[last] = np.zeros(0, dtype=bool)
            return redundant
        a = _Around(p, self.radius_mm)
        near = [_near(a, bins(m).mean, self.T[m]) for m in range(last) if m not in held]
        others = [self.mine[j][~redundant[j]] for j in self.held]
        redundant[last] = measured_elsewhere(p, others, self.radius_mm, a, near)
        return redundant


def _near(a: _Around, mean: NDArray[np.float64], T_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """A registered view's voxel means ``mean`` (mm, at its kinematic pose) moved by its refinement ``T_m``,
    those near the held view of ``a`` (:meth:`_Around.select`)."""
    lo, hi = a.lo, a.hi
    corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), axis=-1).reshape(-1, 3)
    # the box at the view's kinematic pose holds its part of the refined one: grown by the most the inverse
    # correction moves a corner (a rigid motion moves no point of the box farther)
    grow = float(np.linalg.norm(transform_points(invert(T_m), corners) - corners, axis=1).max())
    return a.select(transform_points(T_m, mean[_in_box(mean, lo - grow, hi + grow)]))


def _in_box(points: NDArray[np.float64], lo: NDArray[Any], hi: NDArray[Any]) -> NDArray[np.int64]:
    """Indices of ``points`` (N, 3) inside the box [lo, hi]: x tested on all, y and z on those left."""
    idx = np.flatnonzero((points[:, 0] >= lo[0]) & (points[:, 0] <= hi[0]))
    for j in (1, 2):
        c = points[idx, j]
        idx = idx[(c >= lo[j]) & (c <= hi[j])]
    return idx
