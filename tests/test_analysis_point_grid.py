"""The point grid's answers are scipy's: nearest-other distances as cKDTree.query gives them, radius groups as
connected_components of cKDTree.query_pairs numbers them -- on clouds with duplicates, ties at the radius,
clusters and a point far from the rest."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cell.analysis._point_grid import nearest_other, point_grid, radius_groups


def clouds() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(4)
    sphere = rng.normal(size=(20_000, 3))
    sphere = 50.0 * sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    lattice = np.stack(np.meshgrid(*[np.arange(12.0) * 0.5] * 3, indexing="ij"), -1).reshape(-1, 3)
    dup = np.vstack([sphere[:3000], sphere[:500], sphere[:40], sphere[:40]])  # up to 4 copies of a point
    blobs = np.vstack([rng.normal(c, 0.3, size=(300, 3)) for c in ((0, 0, 0), (5, 0, 0), (5, 4, 1))])
    return {
        "sphere": sphere,
        "lattice (ties at the radius)": lattice,
        "duplicates": dup,
        "blobs and a far point": np.vstack([blobs, [[400.0, -300.0, 90.0]]]),
        "two points": np.array([[0.0, 0, 0], [3.0, 4.0, 0]]),
        "one point twice": np.array([[1.0, 2, 3], [1.0, 2, 3]]),
    }


@pytest.mark.parametrize("name", list(clouds()))
def test_nearest_other_is_what_a_kd_tree_finds(name: str) -> None:
    pts = clouds()[name]
    queries = np.arange(len(pts)) if len(pts) < 5000 else np.random.default_rng(1).choice(len(pts), 4000)
    n_same, d = nearest_other(point_grid(pts), queries)
    k = min(len(pts), 12)
    dist = np.asarray(cKDTree(pts).query(pts[queries], k=k)[0]).reshape(len(queries), k)
    want_same = (dist == 0).sum(1)
    assert (n_same == want_same).all() or (want_same == k).any()  # more copies than k: counted in full
    positive = np.where(dist > 0, dist, np.inf).min(1)
    known = want_same < k
    np.testing.assert_array_equal(d[known], positive[known])


@pytest.mark.parametrize("name", list(clouds()))
@pytest.mark.parametrize("radius", [0.0, 0.5, 1.3, 7.0])
def test_radius_groups_are_the_connected_components_of_the_pairs(name: str, radius: float) -> None:
    pts = clouds()[name]
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(pts), len(pts)))
    _, want = connected_components(graph, directed=False)
    np.testing.assert_array_equal(radius_groups(pts, radius), want)
