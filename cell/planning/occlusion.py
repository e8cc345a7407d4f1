"""Occlusion tests by ray casting against the part mesh (Embree through embreex).

embreex is used directly because trimesh's ray wrapper has no "any hit closer than d" query, which is exactly
the shadow / line-of-sight test, and is several times slower on it. Coordinates are shifted to the mesh centre
before the float32 conversion Embree needs.
"""

from __future__ import annotations

import numpy as np
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from numpy.typing import NDArray

Array = NDArray[np.float64]

OFFSET_MM = 0.05  # rays start this far off the surface (along the normal) so they miss their own triangle


class Occluder:
    """Line-of-sight queries against one mesh in world coordinates (mm)."""

    def __init__(self, mesh: trimesh.Trimesh):
        self._origin = np.asarray(mesh.bounds, dtype=np.float64).mean(axis=0)
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._scene,
            vertices=(np.asarray(mesh.vertices) - self._origin).astype(np.float32),
            indices=np.asarray(mesh.faces, dtype=np.int32),
        )

    def occluded(self, points: Array, normals: Array, dirs: Array, dist: Array) -> NDArray[np.bool_]:
        """True where the segment from each surface point (lifted along its normal) along unit ``dirs`` for
        ``dist`` mm hits the mesh."""
        if len(points) == 0:
            return np.zeros(0, dtype=bool)
        o = (points + OFFSET_MM * normals - self._origin).astype(np.float32)
        res = self._scene.run(
            o,
            np.asarray(dirs, dtype=np.float32),
            dists=np.maximum(np.asarray(dist) - OFFSET_MM, 0).astype(np.float32),
            query="OCCLUDED",
        )
        return np.asarray(res) != -1

    def first_hit(self, origins: Array, dirs: Array) -> tuple[NDArray[np.int64], Array]:
        """Triangle index (-1 on a miss) and distance (inf on a miss) of the first hit of each ray."""
        res = self._scene.run(
            (np.asarray(origins) - self._origin).astype(np.float32),
            np.asarray(dirs, dtype=np.float32),
            output=1,
        )
        tri = np.asarray(res["primID"]).astype(np.int64)
        dist = np.where(tri >= 0, np.asarray(res["tfar"], dtype=np.float64), np.inf)
        return tri, dist
