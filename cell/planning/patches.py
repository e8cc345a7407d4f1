"""Cluster CAD triangles into smooth patches (dissertation Fig. 3.3, eqs 3.1-3.2).

Region growing over shared edges: a triangle joins the patch when the angle between its normal and the
patch's area-weighted mean normal (eq 3.1) is within the patch cone, and within the cone of the seed's normal
too so a slowly curving surface cannot drift around a corner. Seeds are taken largest triangle first.
Written by hand because no well-kept library offers constrained region growing on meshes (trimesh's ``facets``
only
groups exactly coplanar faces); the per-face work is a queue pop and a dot product.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.sparse import coo_matrix


def face_neighbours(mesh: trimesh.Trimesh) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """CSR (indptr, indices) of faces sharing an edge."""
    adj = np.asarray(mesh.face_adjacency)
    n = len(mesh.faces)
    if len(adj) == 0:
        return np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    m = coo_matrix(
        (np.ones(2 * len(adj)), (np.r_[adj[:, 0], adj[:, 1]], np.r_[adj[:, 1], adj[:, 0]])), shape=(n, n)
    ).tocsr()
    return m.indptr.astype(np.int64), m.indices.astype(np.int64)


def cluster_patches(
    mesh: trimesh.Trimesh, cone_rad: float, eligible: NDArray[np.bool_] | None = None
) -> NDArray[np.int64]:
    """Patch label per face (-1 for faces not ``eligible``, e.g. those facing the table)."""
    normals = np.asarray(mesh.face_normals)
    areas = np.asarray(mesh.area_faces)
    n = len(normals)
    label = np.full(n, -1, dtype=np.int64)
    todo = np.ones(n, dtype=bool) if eligible is None else eligible.copy()
    indptr, indices = face_neighbours(mesh)
    cos_cone = np.cos(cone_rad)
    current = 0
    for seed in np.argsort(-areas, kind="stable"):
        if not todo[seed]:
            continue
        seed_n = normals[seed]
        acc = normals[seed] * areas[seed]
        mean = seed_n
        label[seed] = current
        todo[seed] = False
        queue = deque([seed])
        while queue:
            f = queue.popleft()
            for g in indices[indptr[f] : indptr[f + 1]]:
                if not todo[g]:
                    continue
                ng = normals[g]
                if ng @ mean >= cos_cone and ng @ seed_n >= cos_cone:
                    label[g] = current
                    todo[g] = False
                    acc = acc + ng * areas[g]
                    mean = acc / np.linalg.norm(acc)
                    queue.append(g)
        current += 1
    return label
