"""Multi-view merge of noisy views of a known plane: noise drops as the weights predict, no bias, no loss."""

from __future__ import annotations

import numpy as np
import pytest

from cell.analysis.merge import (
    cut_unregistered,
    measured_elsewhere,
    merge_view_stream,
    merge_views,
    voxel_subsample_index,
)
from cell.errors import ConfigError


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
    m = merge_views(views, weights, voxel_mm=1.0)
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
    eq = merge_views(views, None, voxel_mm=1.0)
    r_eq = eq.points_mm[:, 2] - _plane(eq.points_mm[:, 0], eq.points_mm[:, 1])
    assert np.sqrt(np.mean(r[overlap3] ** 2)) < 0.8 * np.sqrt(np.mean(r_eq[eq.n_views == 3] ** 2))


def test_no_points_lost_and_views_outside_overlaps_kept() -> None:
    views, weights, _ = _views()
    views[1] = views[1].copy()
    views[1][:5] = np.nan
    m = merge_views(views, weights, voxel_mm=1.0)
    n = sum(len(v) for v in views)
    assert (m.source == -1).sum() == 5 and m.count.sum() == n - 5
    p = np.concatenate(views)
    ok = m.source >= 0
    assert np.allclose(m.weight.sum(), np.concatenate(weights)[ok].sum())
    # Every input point lies in the voxel of its merged point.
    assert np.array_equal(np.floor(p[ok] / 1.0), np.floor(m.points_mm[m.source[ok]] / 1.0))
    # The occupied voxels are exactly those of the inputs: the single-view strips (x < 10, x > 50) remain.
    assert len(m.points_mm) == len(np.unique(np.floor(p[ok]), axis=0))
    assert (m.points_mm[:, 0] < 10).sum() == 200 and (m.points_mm[:, 0] > 50).sum() == 200


def test_bad_input() -> None:
    with pytest.raises(ConfigError):
        merge_views([np.full((3, 3), np.nan)])
    with pytest.raises(ConfigError):
        merge_views([np.zeros((3, 3))], voxel_mm=0.0)


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
    merge must not get both (the second would sit beside the first as a false deviation)."""
    rng = np.random.default_rng(4)
    registered = np.column_stack([rng.uniform(-20, 0, (4000, 2)), np.zeros(4000)])
    first = np.column_stack([rng.uniform(10, 30, (4000, 2)), np.zeros(4000)])
    second = np.column_stack([rng.uniform(10, 30, (4000, 2)), np.full(4000, 0.4)])
    points = [registered, first, second]
    weights = [np.ones(len(p)) for p in points]
    cut = cut_unregistered(points, weights, [1, 2], radius_mm=2.0)
    assert len(points[0]) == 4000 and len(points[1]) == 4000  # nothing registered there: the first stays
    assert len(points[2]) == len(weights[2]) == 0 and cut == 4000  # the second repeats the first


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
    assert len(merge_views([pts], voxel_mm=1.0).points_mm) == len(idx)
    assert len(voxel_subsample_index(np.zeros((0, 3)), 1.0)) == 0


def test_the_merge_read_view_by_view_is_the_merge_of_all_points_together() -> None:
    """Views given one at a time (each widening the occupied box: a voxel's number must not change when a
    later view adds voxels below it) merge to the voxels of all points taken together: numbered in the
    order of their cells (x, y, z), each with its distinct views and the sums of its points."""
    rng = np.random.default_rng(5)
    views = [rng.uniform(lo, lo + 6, (300, 3)) for lo in (4.0, -3.0, 9.0, 0.5)]
    weights = [rng.uniform(0.5, 2.0, 300) for _ in views]
    read: list[int] = []

    def once() -> list[tuple[np.ndarray, ...]]:
        read.append(len(read))
        return list(zip(views, weights, strict=True))

    numbers: dict[int, np.ndarray] = {}
    m = merge_view_stream(lambda: iter(once()), 1.0, lambda k, at, n, w, extra: numbers.setdefault(k, at))
    assert m is not None and m.source is None and len(read) == 2  # two passes over the views
    cells = np.floor(np.concatenate(views)).astype(int)
    order = sorted({tuple(c) for c in cells})  # the occupied voxels, counted independently
    number = {c: i for i, c in enumerate(order)}
    assert np.array_equal(np.concatenate([numbers[k] for k in range(4)]), [number[tuple(c)] for c in cells])
    of_view = [set(map(tuple, np.floor(v).astype(int))) for v in views]
    seen = [sum(c in s for s in of_view) for c in order]
    assert m.n_views.tolist() == seen
    w = np.concatenate(weights)
    at = np.array([number[tuple(c)] for c in cells])
    assert np.allclose(m.weight, np.bincount(at, weights=w)) and m.count.sum() == 1200
    assert np.allclose(m.points_mm[:, 0], np.bincount(at, weights=w * np.concatenate(views)[:, 0]) / m.weight)
    same = merge_views(views, weights, voxel_mm=1.0)
    assert same.points_mm.tobytes() == m.points_mm.tobytes() and same.source is not None
    assert np.array_equal(same.source, at)
