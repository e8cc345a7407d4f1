"""Single-linkage clustering of 3D points (section 3.3.1's hierarchical clustering, cut at a link length).

Single linkage cut at distance r equals the connected components of the graph joining points closer than r;
SciPy's KD-tree pair query and sparse connected components compute that in O(n log n), where
``scipy.cluster.hierarchy`` would need the O(n^2) distance matrix.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def cluster_points(points: NDArray[np.float64], link_mm: float) -> NDArray[np.int64]:
    """Cluster label per point (0..K-1), largest cluster first."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(link_mm, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    order = np.argsort(-np.bincount(lab), kind="stable")
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    return remap[lab].astype(np.int64)
