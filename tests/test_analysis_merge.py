"""Multi-view merge of noisy views of a known plane: noise drops as the weights predict, no bias, no loss; the
merge of views binned as they arrive (at their kinematic poses) and moved by their refinement at the end."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from cell.analysis.merge import (
    HeldCut,
    MergedCloud,
    ViewBins,
    bin_view,
    held_redundant,
    load_kernels,
    measured_elsewhere,
    merge_bins,
    merge_bins_ahead,
    voxel_subsample_index,
)
from cell.errors import ConfigError
from cell.geometry import transform_points


def merge(
    views: list[np.ndarray],
    weights: list[np.ndarray] | None = None,
    voxel_mm: float = 0.2,
    T: list[np.ndarray] | None = None,
) -> MergedCloud | None:
    """The registration's merge of views given in memory: each binned, moved by ``T`` (default: none)."""
    ws = weights or [np.ones(len(v)) for v in views]
    binned = [bin_view(v, w, None, voxel_mm) for v, w in zip(views, ws, strict=True)]
    n = len(views)
    return merge_bins(voxel_mm, lambda k: binned[k], [None] * n, T or [np.eye(4)] * n)


def _plane(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    # Known surface, kept inside one 1 mm voxel layer (0.5..0.62 mm) so voxel borders never split noise.
    return 0.5 + 0.002 * x + 0.0005 * y


def _views() -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Three views with different noise, overlapping in x: [0, 40], [20, 60], [10, 50] (mm)."""
    rng = np.random.default_rng(21)
    views, weights, truth = [], [], []
    for (x0, x1), sigma in zip([(0, 40), (20, 60), (10, 50)], [0.02, 0.04, 0.08], strict=True):
        n = 40 * (x1 - x0) * 20
        xy = rng.uniform([x0, 0], [x1, 20], (n, 2))
        z = _plane(xy[:, 0], xy[:, 1])
        views.append(np.column_stack([xy, z + rng.normal(0, sigma, n)]))
        weights.append(np.full(n, 1.0 / sigma**2))
        truth.append(z)
    return views, weights, truth


def test_weighted_merge_noise_matches_prediction_without_bias() -> None:
    views, weights, _ = _views()
    m = merge(views, weights, voxel_mm=1.0)
    assert m is not None
    # Residual of each merged point from the known plane: the weighted mean of its points' noise (the plane
    # is linear, so the mean of points on it lies on it). Expected std per voxel: 1 / sqrt(sum w).
    r = m.points_mm[:, 2] - _plane(m.points_mm[:, 0], m.points_mm[:, 1])
    z = r / m.sigma_mm
    assert abs(z.mean()) < 4 / np.sqrt(len(z))  # no bias
    assert z.std() == pytest.approx(1.0, abs=0.05)
    overlap3 = m.n_views == 3
    assert overlap3.sum() > 300
    rms3 = np.sqrt(np.mean(r[overlap3] ** 2))
    assert rms3 == pytest.approx(np.sqrt(np.mean(m.sigma_mm[overlap3] ** 2)), rel=0.1)
    only_best = m.points_mm[:, 0] < 10  # voxels seen by the 0.02 mm view alone
    assert rms3 < 0.92 * np.sqrt(np.mean(r[only_best] ** 2))
    # Equal weights do worse: the noisy view drags the mean.
    eq = merge(views, None, voxel_mm=1.0)
    assert eq is not None
    r_eq = eq.points_mm[:, 2] - _plane(eq.points_mm[:, 0], eq.points_mm[:, 1])
    assert np.sqrt(np.mean(r[overlap3] ** 2)) < 0.8 * np.sqrt(np.mean(r_eq[eq.n_views == 3] ** 2))


def test_no_points_lost_and_views_outside_overlaps_kept() -> None:
    views, weights, _ = _views()
    views[1] = views[1].copy()
    views[1][:5] = np.nan
    m = merge(views, weights, voxel_mm=1.0)
    assert m is not None
    n = sum(len(v) for v in views)
    assert m.count.sum() == n - 5
    p = np.concatenate(views)
    ok = np.isfinite(p).all(1)
    assert np.allclose(m.weight.sum(), np.concatenate(weights)[ok].sum())
    # The occupied voxels are exactly those of the inputs, in the order of their cells (x, then y, then z),
    # each merged point inside its voxel: the single-view strips (x < 10, x > 50) remain.
    cells = np.unique(np.floor(p[ok]).astype(int), axis=0)
    assert np.array_equal(np.floor(m.points_mm).astype(int), cells)
    assert (m.points_mm[:, 0] < 10).sum() == 200 and (m.points_mm[:, 0] > 50).sum() == 200


def test_bad_input() -> None:
    assert merge([np.full((3, 3), np.nan)]) is None
    with pytest.raises(ConfigError):
        merge([np.zeros((3, 3))], voxel_mm=0.0)
    with pytest.raises(ConfigError):
        merge_bins(-1.0, lambda k: bin_view(np.zeros((1, 3)), np.ones(1), None, 0.2), [None], [np.eye(4)])
    with pytest.raises(ConfigError):  # beyond the key's +-2^20 voxels
        merge([np.array([[0.0, 0.0, 3e5]])], voxel_mm=0.2)
    # binned within range, then moved beyond it, or by a pose that is not finite: found by the kernel
    bins = bin_view(np.zeros((2, 3)), np.ones(2), None, 0.2)
    far, nan = np.eye(4), np.full((4, 4), np.nan)
    far[2, 3] = 3e5
    for T in (far, nan):
        with pytest.raises(ConfigError, match="not finite or beyond"):
            merge_bins(0.2, lambda k: bins, [None], [T])
    with pytest.raises(ValueError, match="mask has 3 entries for its 1 bins"):
        merge_bins(0.2, lambda k: bins, [np.ones(3, dtype=bool)], [np.eye(4)])


def test_an_unregistered_view_gives_only_what_no_registered_view_measured() -> None:
    """A view held 0.4 mm off (its kinematic pose) over a plane two registered views measured in part: its
    points over their surface are redundant, the rest (surface only it saw) are kept."""
    rng = np.random.default_rng(3)
    left = np.column_stack([rng.uniform(-20, 0, (5000, 2)), np.zeros(5000)])
    right = np.column_stack([rng.uniform(0, 20, (5000, 1)), rng.uniform(-20, 0, (5000, 1)), np.zeros(5000)])
    held = np.column_stack([rng.uniform(-20, 40, (9000, 2)), np.full(9000, 0.4)])
    redundant = measured_elsewhere(held, [left, right], radius_mm=2.0)
    registered_area = (held[:, 0] < 20) & (held[:, 1] < 0)  # where left and right lie
    far = (held[:, 0] > 22) | (held[:, 1] > 2)  # beyond the radius of both
    assert redundant[registered_area].all()
    assert not redundant[far].any()
    assert not measured_elsewhere(held, [], radius_mm=2.0).any()


def test_two_unregistered_views_over_one_spot_give_it_once() -> None:
    """Two unregistered views 0.4 mm apart over the same surface, which no registered view measured: the
    merge must not get both (the second would sit beside the first as a false deviation); and a registered
    view's voxels are taken where its refinement moved them (here 12 mm along x: over the first's edge)."""
    rng = np.random.default_rng(4)
    registered = np.column_stack([rng.uniform(-20, 0, (4000, 2)), np.zeros(4000)])
    first = np.column_stack([rng.uniform(10, 30, (4000, 2)), np.zeros(4000)])
    second = np.column_stack([rng.uniform(10, 30, (4000, 2)), np.full(4000, 0.4)])
    binned = [bin_view(p, np.ones(len(p)), None, 0.2) for p in (registered, first, second)]
    T = [np.eye(4)] * 3
    cut = held_redundant(lambda k: binned[k], T, [1, 2], radius_mm=2.0)
    assert sorted(cut) == [1, 2] and not cut[1].any()  # nothing registered there: the first stays whole
    assert cut[2].all()  # the second repeats the first
    shifted = np.eye(4)
    shifted[0, 3] = 12.0  # the registered view's right edge to x = 12: within 2 mm of the first's x < 14
    cut = held_redundant(lambda k: binned[k], [shifted, T[1], T[2]], [1, 2], radius_mm=2.0)
    x = binned[1].mean[:, 0]
    y = binned[1].mean[:, 1]
    assert cut[1][(x < 11.8) & (y < -0.2)].all() and not cut[1][(x > 14.2) | (y > 2.2)].any()


def test_voxel_subsample_keeps_the_first_point_of_each_voxel_of_the_merge_grid() -> None:
    """The one voxel key: the subsample takes one point from each voxel the merge averages."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-5, 5, (4000, 3))
    idx = voxel_subsample_index(pts, 1.0)
    cells = np.floor(pts).astype(int)  # the 1 mm voxels, counted independently
    first = {}
    for i, c in enumerate(map(tuple, cells)):
        first.setdefault(c, i)
    assert idx.tolist() == sorted(first.values())
    merged = merge([pts], voxel_mm=1.0)
    assert merged is not None and len(merged.points_mm) == len(idx)
    assert len(voxel_subsample_index(np.zeros((0, 3)), 1.0)) == 0


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K


def test_the_merge_of_binned_views_is_the_refined_points_merged_bin_by_bin() -> None:
    """Views binned at their kinematic poses and merged with known rigid corrections (a few tenths of a mm and
    of a degree: many bins change voxel) equal, to 1e-9 mm, the refined points merged plainly: each view's
    points grouped by their kinematic voxel, each group moved by the view's correction and put, whole, in
    the voxel its weighted mean moved into; every voxel's weighted mean over all groups in it, the voxels in
    the order of their cells. Counted here point by point in Python, without the merge's code."""
    rng = np.random.default_rng(11)
    voxel = 0.2
    views, weights, T = [], [], []
    for k in range(4):
        xy = rng.uniform(0, 4, (3000, 2)) + 0.7 * k
        views.append(np.column_stack([xy, 0.3 * xy[:, 0] + rng.normal(0, 0.01, len(xy))]))
        weights.append(rng.uniform(0.5, 2.0, len(xy)))
        T_k = np.eye(4)
        T_k[:3, :3] = _rotation(rng.normal(size=3), np.deg2rad(0.2))
        T_k[:3, 3] = rng.uniform(-0.3, 0.3, 3)
        T.append(T_k)
    m = merge(views, weights, voxel, T)
    assert m is not None
    wsum: dict[tuple[int, ...], float] = defaultdict(float)
    psum: dict[tuple[int, ...], np.ndarray] = defaultdict(lambda: np.zeros(3))
    n_views: dict[tuple[int, ...], set[int]] = defaultdict(set)
    for k, (p, w) in enumerate(zip(views, weights, strict=True)):
        groups: dict[tuple[int, ...], list[int]] = defaultdict(list)
        for i, c in enumerate(np.floor(p / voxel).astype(int)):
            groups[tuple(c)].append(i)
        moved = transform_points(T[k], p)
        for idx in groups.values():
            g_w = w[idx]
            mean = (g_w[:, None] * moved[idx]).sum(0) / g_w.sum()
            cell = tuple(np.floor(mean / voxel).astype(int))
            wsum[cell] += g_w.sum()
            psum[cell] += (g_w[:, None] * moved[idx]).sum(0)
            n_views[cell].add(k)
    cells = sorted(wsum)
    expected = np.array([psum[c] / wsum[c] for c in cells])
    assert len(m.points_mm) == len(cells)
    assert np.abs(m.points_mm - expected).max() < 1e-9
    assert np.allclose(m.weight, [wsum[c] for c in cells], rtol=1e-12)
    assert m.n_views.tolist() == [len(n_views[c]) for c in cells] and m.count.sum() == 12000
    # the corrections mattered: binned at the kinematic voxels the groups would fill other voxels
    kinematic = {tuple(c) for p in views for c in np.floor(p / voxel).astype(int)}
    assert len(kinematic.symmetric_difference(cells)) > 1000


def _reference_merge(
    bins: list[ViewBins], keep: list[np.ndarray | None], T: list[np.ndarray], voxel: float
) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """The merge with NumPy's group-by (the registration's before its compiled kernel): each view's moved
    means put in the voxels they fall in (all voxels sorted by cell, ``np.unique``), a view's sums per voxel
    by a stable sort and ``np.add.reduceat``, added to the voxels' in view order."""
    moved = [
        transform_points(t, b.mean) if k is None else transform_points(t, b.mean)[k]
        for b, k, t in zip(bins, keep, T, strict=True)
    ]
    cells = [np.floor(p / voxel).astype(np.int64) for p in moved]
    every, at = np.unique(np.concatenate(cells), axis=0, return_inverse=True)
    m = len(every)
    wsum, sums, count, given = np.zeros(m), np.zeros((3, m)), np.zeros(m, np.int64), np.zeros(m, np.int64)
    views, start = [], 0
    for b, k, p in zip(bins, keep, moved, strict=True):
        rows = at.ravel()[start : start + len(p)]
        start += len(p)
        w, c, wu = (b.weight, b.count, b.wu) if k is None else (b.weight[k], b.count[k], b.wu[k])
        order = np.argsort(rows, kind="stable")
        first = np.r_[True, rows[order][1:] != rows[order][:-1]]
        starts = np.flatnonzero(first)
        r = rows[order][starts]

        def per_row(x: np.ndarray) -> np.ndarray:
            return np.add.reduceat(x[order], starts)  # noqa: B023

        w_rows = per_row(w)
        wsum[r] += w_rows
        for j in range(3):
            sums[j][r] += per_row(w * p[:, j])
        count[r] += per_row(c.astype(np.float64)).astype(np.int64)
        given[r] += 1
        views.append((r, w_rows, per_row(wu.astype(np.float64))))
    return [(sums / wsum).T.copy(), wsum, count, given], views


def test_the_compiled_merge_is_numpys_group_by_to_the_bit() -> None:
    """Five views (two with held masks) moved by corrections of tens of um and 0.3 deg (many bins change
    voxel), and one whose dozen bins all fall in one voxel (NumPy's pairwise sum of more than 8): the merge's
    points, weights, counts, views per voxel and each view's shares equal NumPy's group-by byte for byte."""
    load_kernels()  # (as the decode worker loads them: then the merge's first call compiles nothing)
    rng = np.random.default_rng(17)
    voxel = 0.2
    bins, keep, T = [], [], []
    for k in range(5):
        b, T_k = _refined_view(rng, rng.uniform(0, 4, (1500, 2)) + 0.3 * k, voxel)
        bins.append(b)
        T.append(T_k)
        keep.append(rng.random(len(bins[-1])) < 0.7 if k in (1, 3) else None)
        moved_cells = np.floor(transform_points(T_k, bins[-1].mean) / voxel)
        assert (moved_cells != np.floor(bins[-1].mean / voxel)).any(1).mean() > 0.05  # some change voxel
    crowd = ViewBins(  # (not from bin_view: a dozen means in one voxel)
        rng.uniform(1.01, 1.19, (12, 3)),
        rng.uniform(0.5, 2.0, 12),
        rng.uniform(0, 0.1, 12).astype(np.float32),
        np.ones(12, np.int32),
    )
    bins.append(crowd)
    keep.append(None)
    T.append(np.eye(4))
    got: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def each_view(k: int, rows: np.ndarray, m: int, w: np.ndarray, wu: np.ndarray) -> None:
        assert k == len(got)
        got.append((rows.astype(np.int64), w, wu))

    merged = merge_bins(voxel, lambda k: bins[k], keep, T, each_view)
    want, want_views = _reference_merge(bins, keep, T, voxel)
    assert merged is not None and len(merged.points_mm) > 500
    for a, b in zip((merged.points_mm, merged.weight, merged.count, merged.n_views), want, strict=True):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    for a_view, b_view in zip(got, want_views, strict=True):
        for a, b in zip(a_view, b_view, strict=True):
            assert a.tobytes() == b.tobytes()
    assert merged.n_views.max() >= 3 and merged.count.sum() == sum(
        int(b.count.sum() if k is None else b.count[k].sum()) for b, k in zip(bins, keep, strict=True)
    )


def _refined_views(rng: np.random.Generator, n: int, voxel: float) -> tuple[list, list, list]:
    """``n`` binned patches of a sloped surface, overlapping, with refinements of tens of um and 0.3 deg and
    a held mask on every third: the merge's inputs."""
    bins, keep, T = [], [], []
    for k in range(n):
        b, T_k = _refined_view(rng, rng.uniform(0, 3, (900, 2)) + 0.4 * k, voxel)
        bins.append(b)
        T.append(T_k)
        keep.append(rng.random(len(bins[-1])) < 0.7 if k % 3 == 1 else None)
    return bins, keep, T


def _refined_view(rng: np.random.Generator, xy: np.ndarray, voxel: float) -> tuple[ViewBins, np.ndarray]:
    """A patch of the sloped surface z = 0.4 y over ``xy`` (mm) with 10 um of noise, binned with random
    weights and u, and a refinement of tens of um and 0.3 deg."""
    p = np.column_stack([xy, 0.4 * xy[:, 1] + rng.normal(0, 0.01, len(xy))])
    bins = bin_view(p, rng.uniform(0.5, 2.0, len(p)), rng.uniform(0.005, 0.02, len(p)), voxel)
    T = np.eye(4)
    T[:3, :3] = _rotation(rng.normal(size=3), np.deg2rad(0.3))
    T[:3, 3] = rng.uniform(-0.06, 0.06, 3)
    return bins, T


def _merged_with_views(merged: MergedCloud | None, calls: list) -> list[bytes]:
    """Every array of a merge and of its ``each_view`` calls, as bytes (with their dtypes and m)."""
    if merged is None:
        return [b"None"] + [repr(c).encode() for c in calls]
    out = [x.dtype.str.encode() + x.tobytes() for x in (merged.points_mm, merged.weight, merged.count)]
    out.append(merged.n_views.tobytes())
    for k, rows, m, w, wu in calls:
        out += [f"{k} {m} {rows.dtype}".encode(), rows.tobytes(), w.tobytes(), wu.tobytes()]
    return out


@pytest.mark.parametrize(
    "last", ["new voxels", "old voxels", "repeated", "crowd", "nothing", "nothing before"]
)
def test_a_merge_made_ahead_and_finished_with_the_last_view_is_the_full_merge_to_the_bit(last: str) -> None:
    """Four views merged ahead, then the last: a view beside them (its voxels new, all before theirs), one
    over them (moved by its own refinement: some voxels new, most shared), a copy of an earlier view (no
    new voxel: the same numbering), a dozen bins in one new voxel (NumPy's pairwise sum), a view whose bins
    are all held back, and earlier views that give nothing: points, weights, counts, views per voxel and
    every view's ``each_view`` arguments equal the merge of all five at once, byte for byte."""
    load_kernels()
    rng = np.random.default_rng({"new voxels": 1, "old voxels": 2, "repeated": 3}.get(last, 4))
    voxel = 0.2
    bins, keep, T = _refined_views(rng, 5, voxel)
    if last == "new voxels":
        bins[4] = bin_view(bins[4].mean - [6.0, 0.0, 0.0], bins[4].weight, None, voxel)
    elif last == "repeated":
        bins[4], keep[4], T[4] = bins[2], None, T[2]
    elif last == "crowd":
        bins[4] = ViewBins(
            rng.uniform(8.01, 8.19, (12, 3)),
            rng.uniform(0.5, 2.0, 12),
            rng.uniform(0, 0.1, 12).astype(np.float32),
            np.ones(12, np.int32),
        )
        keep[4] = None
    elif last == "nothing":
        keep[4] = np.zeros(len(bins[4]), dtype=bool)
    elif last == "nothing before":
        keep[:4] = [np.zeros(len(b), dtype=bool) for b in bins[:4]]
    full: list = []
    merged = merge_bins(voxel, lambda k: bins[k], keep, T, lambda *a: full.append(a))
    partial = merge_bins_ahead(voxel, lambda k: bins[k], keep[:4], T[:4])
    two: list = []
    finished = partial.finish(bins[4], keep[4], T[4], lambda *a: two.append(a))
    assert merged is not None and len(full) == 5 and [c[0] for c in two] == list(range(5))
    if last in ("repeated", "nothing"):
        assert len(merged.weight) == len(partial.wsum)  # (no voxel added: the numbering kept)
    else:
        assert len(merged.weight) > len(partial.wsum)
    assert _merged_with_views(finished, two) == _merged_with_views(merged, full)
    with pytest.raises(RuntimeError):
        partial.finish(bins[4], keep[4], T[4])


@pytest.mark.parametrize(
    "last", ["registered apart", "registered over a held", "held over a held", "held apart", "none held"]
)
def test_a_held_cut_made_ahead_and_finished_with_the_last_view_is_the_full_cut(last: str) -> None:
    """Five patches side by side (x 0-4, 3-7, 6-10, 9-13, 12-16 mm; views 1 and 2 held, overlapping each
    other and view 0) and a last view, registered or held, beside them (x 30-34) or over held view 2 (x
    8-12): the cut made ahead of the last and finished with it equals :func:`held_redundant` of all six,
    byte for byte; a registered last view over a held one cuts it further (the ahead cut made again)."""
    rng = np.random.default_rng(5)
    voxel, radius = 0.2, 1.0
    x0 = [0.0, 3.0, 6.0, 9.0, 12.0, 30.0 if "apart" in last else 8.0]
    bins, T = [], []
    for k, x in enumerate(x0):
        xy = rng.uniform([x, 0.0], [x + 4.0, 4.0], (700, 2))
        p = np.column_stack([xy, 0.1 * k + rng.normal(0, 0.01, len(xy))])
        bins.append(bin_view(p, np.ones(len(p)), None, voxel))
        T_k = np.eye(4)
        T_k[:3, :3] = _rotation(rng.normal(size=3), np.deg2rad(0.2))
        T_k[:3, 3] = rng.uniform(-0.05, 0.05, 3)
        T.append(T_k)
    held = [] if last == "none held" else [1, 2] + ([5] if last.startswith("held") else [])
    full = held_redundant(lambda k: bins[k], T, held, radius)
    ahead = HeldCut(lambda k: bins[k], T[:5], [k for k in held if k < 5], radius)
    asked: list[int] = []

    def asked_bins(k: int) -> ViewBins:
        asked.append(k)
        return bins[k]

    two = ahead.with_last(asked_bins, T, held)
    assert list(two) == list(full) and all(two[k].tobytes() == full[k].tobytes() for k in full)
    if last == "registered over a held":
        assert (full[2] != ahead.redundant[2]).any()  # the last view cut more of view 2: made again
    elif last != "none held":
        assert set(asked) <= {0, 3, 4, 5}  # the held views' own bins were not needed again
    if last.startswith("held"):
        assert full[5].any() != (last == "held apart")  # cut where it repeats view 2, whole where apart


def test_a_merge_made_ahead_is_kept_until_taken_voided_by_a_view_forgotten_and_fits_only_the_same_bits() -> (
    None
):
    """The registration's :class:`MergeBins` keeps a merge made ahead until the registration takes it, not
    when a view was forgotten while it was made (a view measured again), and none is made of views not
    binned as they arrived; the registration uses it only for the same views, corrections and held views,
    to the bit, and the same masks."""
    from cell.inspection_results import ARRIVAL_BINNING_MAX_POINTS, MergeAhead, MergeBins

    rng = np.random.default_rng(8)
    bins, keep, T = _refined_views(rng, 3, 0.2)
    state = MergeBins(0.2, Path("run"))
    for i, b in zip((2, 5), bins[:2], strict=True):
        state.add(i, b, int(b.count.sum()))
    assert state.bins_ahead([2, 5, 7]) is None  # view 7 not binned
    got = state.bins_ahead([2, 5])
    assert got is not None and got[0][1] is bins[1]
    held = HeldCut(lambda k: bins[k], T[:2], [1], 1.0)
    masks = [None, ~held.redundant[1]]
    ahead = MergeAhead(
        (2, 5), T[:2], (1,), held, masks, {}, merge_bins_ahead(0.2, bins.__getitem__, masks, T[:2])
    )
    state.forget(9)  # another view (the last, as its decode begins): no matter
    assert state.keep_ahead(ahead, got[1])
    state.forget(9)
    assert state.take_ahead() is ahead and state.take_ahead() is None  # kept, then taken once
    state.forget(5)  # one of its views measured again while it was made
    assert not state.keep_ahead(ahead, got[1]) and state.take_ahead() is None
    state.add(5, bins[1], int(bins[1].count.sum()))
    again = state.bins_ahead([2, 5])
    assert again is not None and state.keep_ahead(ahead, again[1])
    state.forget(2)  # ... or after
    assert state.take_ahead() is None
    assert ahead.fits([2, 5, 8], T, [1]) and ahead.fits([2, 5, 8], T, [1, 2])  # the last held or not
    nudged = T[1].copy()
    nudged[0, 3] = np.nextafter(nudged[0, 3], 1.0)
    assert not ahead.fits([2, 5, 8], [T[0], nudged, T[2]], [1])  # a correction one ulp apart
    assert not ahead.fits([2, 5, 8], T, []) and not ahead.fits([2, 5, 8], T, [0, 1])  # other held views
    assert not ahead.fits([2, 6, 8], T, [1]) and not ahead.fits([2, 5, 4], T, [1])  # other views, order
    assert not ahead.fits([2, 5], T[:2], [1])  # no last view
    assert ahead.keeps([None, masks[1], None]) and not ahead.keeps([None, ~masks[1], None])
    assert not ahead.keeps([masks[1], masks[1], None])
    big = ARRIVAL_BINNING_MAX_POINTS + 1
    state.add(7, bins[2], big)  # a 5 MP camera's view: binned when merged, never merged ahead
    assert state.bins_ahead([2, 5, 7]) is None


def test_view_bins_hold_the_points_weighted_sums() -> None:
    """A view's bins: per voxel the weighted mean, the weight sum, the weighted u sum and the count."""
    p = np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [0.25, 0.05, 0.05]])
    bins = bin_view(p, np.array([1.0, 3.0, 2.0]), np.array([0.01, 0.02, 0.04]), 0.2)
    assert isinstance(bins, ViewBins) and len(bins) == 2
    assert np.allclose(bins.mean[0], [0.125, 0.05, 0.05]) and np.allclose(bins.mean[1], p[2])
    assert bins.weight.tolist() == [4.0, 2.0] and bins.count.tolist() == [2, 1]
    assert np.allclose(bins.wu, [0.07, 0.08])
