"""A smooth-shaded triangle surface for specular ray tracing: Embree hit, float64 refinement, smooth normals.

Reflection doubles every normal error, so the flat facet normal of a tessellated pane (a kink of ~0.5 mrad
between 2 mm facets of a 2 m radius) would break every marker image and every reflection-law test. The
surface therefore reports the hit point on the facet (Embree in float32, refined by the exact float64
ray/plane intersection on the triangle it found) and the normal interpolated from the vertex normals with the
barycentric coordinates of that point (Phong normal), which is continuous across facets.

embreex is used directly (not trimesh's ray wrapper): one ``run(..., output=1)`` call returns triangle ids
and barycentrics for millions of rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.raycast import RayCaster


@dataclass(frozen=True)
class SurfaceHits:
    """First hits of N rays: distance along the unit direction (inf on a miss), the point (mm), the smooth
    unit normal on the side the surface's vertex normals point to (NaN on a miss) and the triangle (-1)."""

    distance: NDArray[np.float64]
    point: NDArray[np.float64]
    normal: NDArray[np.float64]
    triangle: NDArray[np.int64]

    @property
    def hit(self) -> NDArray[np.bool_]:
        return self.triangle >= 0


class SmoothSurface:
    """One triangle mesh (world mm) ready for ray casting with interpolated vertex normals."""

    def __init__(self, mesh: trimesh.Trimesh, vertex_normals: NDArray[np.float64] | None = None) -> None:
        self.vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        vn = np.asarray(mesh.vertex_normals if vertex_normals is None else vertex_normals, dtype=np.float64)
        self.vertex_normals = vn / np.linalg.norm(vn, axis=1, keepdims=True)
        self._caster = RayCaster(self.vertices, self.faces, what="surface")
        self._tri = self._caster.triangles

    def cast(self, origins: NDArray[np.float64], dirs: NDArray[np.float64]) -> SurfaceHits:
        """First hit of rays (N, 3) from ``origins`` along unit ``dirs`` (world mm)."""
        tri, distance, o, d = self._caster.first_hits(origins, dirs)
        hit = tri >= 0
        point = np.full((len(d), 3), np.nan)
        normal = np.full((len(d), 3), np.nan)
        point[hit] = o[hit] + distance[hit, None] * d[hit]
        if np.any(hit):
            normal[hit] = self.normals_at(point[hit], tri[hit])
        return SurfaceHits(distance, point, normal, tri)

    def normals_at(self, points: NDArray[np.float64], triangles: NDArray[np.int64]) -> NDArray[np.float64]:
        """Phong normals at points lying on the given triangles: barycentric blend of the vertex normals."""
        tri = self._tri[triangles]
        e1, e2, r = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], points - tri[:, 0]
        d11, d12, d22 = (np.einsum("ij,ij->i", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
        r1, r2 = np.einsum("ij,ij->i", r, e1), np.einsum("ij,ij->i", r, e2)
        den = d11 * d22 - d12 * d12
        b1 = (d22 * r1 - d12 * r2) / den
        b2 = (d11 * r2 - d12 * r1) / den
        vn = self.vertex_normals[self.faces[triangles]]
        n = (1 - b1 - b2)[:, None] * vn[:, 0] + b1[:, None] * vn[:, 1] + b2[:, None] * vn[:, 2]
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def reflect(d: NDArray[np.float64], n: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mirror directions ``d`` (N, 3) about unit normals ``n``: d - 2 (d.n) n."""
    return d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n


def unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Vectors (..., 3) scaled to unit length."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotate(R: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotate rows of ``v`` (N, 3) by the 3x3 ``R``.

    Written column-wise instead of ``v @ R.T``: numpy's matmul with a 3-wide inner dimension is ~10x slower
    for millions of rows and copies broadcast views.
    """
    v = np.asarray(v, dtype=np.float64)
    return v[:, 0:1] * R[:, 0] + v[:, 1:2] * R[:, 1] + v[:, 2:3] * R[:, 2]


def plane_hits(
    origins: NDArray[np.float64], dirs: NDArray[np.float64], T_W_S: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N, 2) coordinates (mm) in the plane z=0 of {S} where rays from its front (+z side) meet it; NaN
    where a ray misses, runs away from it or starts behind it."""
    R_S_W = T_W_S[:3, :3].T
    o = rotate(R_S_W, np.asarray(origins, dtype=np.float64) - T_W_S[:3, 3])
    d = rotate(R_S_W, dirs)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[:, 2] / d[:, 2]
    ok = (s > 0) & (d[:, 2] < 0) & (o[:, 2] > 0)
    xy = o[:, :2] + s[:, None] * d[:, :2]
    return np.where(ok[:, None], xy, np.nan)
