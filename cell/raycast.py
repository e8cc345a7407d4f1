"""First-hit ray casting on a triangle mesh: Embree finds the triangle, float64 geometry gives the distance.

Embree (through embreex, the binding trimesh uses) is the fastest ray caster available, but it computes in
float32, whose intersection error grows with the distance from the origin. The cell needs micrometres, so
Embree is used only to find *which* triangle a ray hits (in coordinates centred on the mesh, where float32 has
the most resolution) and the distance is recomputed exactly as the intersection with that triangle's plane.
It is the cell's one ray caster: the simulator's scene, the glass surface, the planner's occlusion tests and
the inspection's rays onto the nominal all use it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from numpy.typing import NDArray


class RayCaster:
    """A triangle mesh (world mm) ready for first-hit and occlusion queries."""

    def __init__(self, vertices: NDArray[np.float64], faces: NDArray[np.int64], what: str = "mesh") -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError(f"{what} has degenerate (zero-area) triangles; clean the mesh first")
        self.triangles = tri
        self.face_normals = n / norm
        self.plane_d = np.einsum("ij,ij->i", self.face_normals, tri[:, 0])  # n . x = d on each triangle
        self._origin = 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._embree,
            vertices=(self.vertices - self._origin).astype(np.float32),
            indices=self.faces.astype(np.int32),
        )

    def _run(self, origins: NDArray[np.float64], dirs: NDArray[np.float64], **kw: Any) -> Any:
        """Embree's query on rays relative to the mesh centre (float32 keeps its resolution there)."""
        o = (np.asarray(origins, dtype=np.float64) - self._origin).astype(np.float32)
        return self._embree.run(o, np.asarray(dirs, dtype=np.float32), **kw)

    def first_hits(
        self, origins: NDArray[np.float64], dirs: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """For rays (N, 3) from ``origins`` (one or N) along unit ``dirs``: the triangle hit (-1 on a miss),
        the exact float64 distance (inf on a miss), and the broadcast origins and directions used."""
        dirs = np.ascontiguousarray(np.asarray(dirs, dtype=np.float64).reshape(-1, 3))
        origins = np.ascontiguousarray(
            np.broadcast_to(np.asarray(origins, np.float64).reshape(-1, 3), dirs.shape)
        )
        tri = np.asarray(self._run(origins, dirs, output=1)["primID"]).astype(np.int64)
        hit = tri >= 0
        distance = np.full(len(dirs), np.inf)
        t = tri[hit]
        n = self.face_normals[t]
        distance[hit] = (self.plane_d[t] - np.einsum("ij,ij->i", origins[hit], n)) / np.einsum(
            "ij,ij->i", dirs[hit], n
        )
        return np.where(hit, tri, -1), distance, origins, dirs

    def first_hit_points(
        self, origins: NDArray[np.float64], dirs: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """For rays as in :meth:`first_hits`: the triangle hit (-1 on a miss) and the hit point (mm, float64;
        NaN on a miss)."""
        tri, distance, origins, dirs = self.first_hits(origins, dirs)
        hit = tri >= 0
        points = np.full(dirs.shape, np.nan)
        points[hit] = origins[hit] + distance[hit, None] * dirs[hit]
        return tri, points

    def occluded(
        self, origins: NDArray[np.float64], dirs: NDArray[np.float64], max_distance: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """True where something lies on the ray closer than ``max_distance`` (mm): the shadow test."""
        if len(origins) == 0:
            return np.zeros(0, dtype=bool)
        res = self._run(origins, dirs, dists=np.asarray(max_distance, dtype=np.float32), query="OCCLUDED")
        return np.asarray(res) != -1
