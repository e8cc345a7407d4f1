"""The compiled pose uncertainty of merged points (cell/analysis/_pose_kernel.py) against the dense formula it
replaces: every point's sqrt(l C l^T) with l = s (x) r - r B over all 6n pose parameters, computed by numpy.

Truth: the definition, evaluated densely, on shares as a merge gives them (most points of one or two views,
some of several, zero shares elsewhere) and on shares with every view in every point."""

from __future__ import annotations

import numpy as np
import pytest

from cell.analysis._pose_kernel import pose_sigma


def _dense(shares: np.ndarray, rows: np.ndarray, C: np.ndarray, B: np.ndarray | None) -> np.ndarray:
    n = shares.shape[1]
    L = (shares[:, :, None] * rows[:, None, :]).reshape(len(rows), 6 * n)
    if B is not None:
        L -= rows @ B
    return np.sqrt(np.maximum(np.einsum("ij,ij->i", L @ C, L), 0.0))


@pytest.mark.parametrize("dense_shares", [False, True])
def test_pose_sigma_is_the_dense_quadratic_form(dense_shares: bool) -> None:
    rng = np.random.default_rng(3)
    n, m = 7, 4000
    if dense_shares:
        shares = rng.random((m, n))
    else:
        shares = np.zeros((m, n))
        for p in range(m):
            views = rng.choice(n, size=rng.integers(1, 4), replace=False)
            shares[p, views] = rng.random(len(views)) + 0.01
    shares /= shares.sum(axis=1, keepdims=True)
    rows = rng.normal(size=(m, 6))
    A = rng.normal(size=(6 * n, 6 * n)) * 0.02
    C = A @ A.T  # a covariance: symmetric, positive semi-definite
    B = rng.normal(size=(6, 6 * n)) / n
    for Bm in (None, B):
        want = _dense(shares, rows, C, Bm)
        assert pose_sigma(shares, rows, C, Bm) == pytest.approx(want, rel=1e-9, abs=1e-12)


def test_datum_neighbourhoods_are_the_kd_trees() -> None:
    """The merged points near each datum (whose view shares the datum alignment's map takes), found without a
    tree of the whole cloud: the same points as scipy's cKDTree.query_ball_point."""
    from scipy.spatial import cKDTree

    from cell.geometry import points_within

    rng = np.random.default_rng(5)
    points = rng.uniform(-30.0, 30.0, size=(200_000, 3))
    points[:, 2] = np.round(points[:, 2] / 3.0) * 3.0  # stacked sheets, as a part's faces
    tree = cKDTree(points)
    sizes = []
    for _ in range(20):
        centre = points[rng.integers(len(points))] + rng.normal(scale=0.3, size=3)
        radius = float(rng.uniform(0.5, 5.0))
        found = points_within(points, centre, radius)
        assert np.array_equal(found, np.sort(tree.query_ball_point(centre, radius)))
        sizes.append(len(found))
    assert min(sizes) > 0  # every neighbourhood held points to compare
