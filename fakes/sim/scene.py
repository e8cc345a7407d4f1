"""The simulated world: the part mesh and the table (plane z=0 of {W}) in one Embree scene, with materials.

Embree (through embreex, used directly because trimesh's wrapper returns every hit and is far slower) works in
float32; each hit is refined in float64 by intersecting the ray exactly with the plane of the triangle it hit,
which puts hit points on a plane within ~1e-9 mm of the analytic intersection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.config import MaterialConfig, SimConfig
from cell.raycast import RayCaster


@dataclass(frozen=True)
class Hits:
    """Result of casting N rays: distance along the unit direction (inf on a miss), triangle index (-1 on a
    miss), unit normal turned to face the incoming ray (NaN on a miss) and whether it is the part."""

    distance: NDArray[np.float64]
    triangle: NDArray[np.int64]
    normal: NDArray[np.float64]
    is_part: NDArray[np.bool_]

    @property
    def hit(self) -> NDArray[np.bool_]:
        return self.triangle >= 0


class Scene:
    """Triangles in world coordinates (mm) with per-triangle material, ready for ray casting."""

    def __init__(
        self,
        vertices_W: NDArray[np.float64],
        faces: NDArray[np.int64],
        is_part: NDArray[np.bool_],
        albedo: NDArray[np.float64],
        specular: NDArray[np.float64],
        shininess: NDArray[np.float64],
        roughness_um: NDArray[np.float64] | None = None,
        grain_mm: NDArray[np.float64] | None = None,
        albedo_texture: NDArray[np.float64] | None = None,
    ):
        self.vertices = np.ascontiguousarray(vertices_W, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.is_part = np.asarray(is_part, dtype=bool)
        self.albedo = np.asarray(albedo, dtype=np.float32)
        self.specular = np.asarray(specular, dtype=np.float32)
        self.shininess = np.asarray(shininess, dtype=np.float32)
        n = len(self.faces)
        # surface microstructure per triangle (rendered only when the renderer is given a world seed for it)
        self.roughness_um = np.zeros(n) if roughness_um is None else np.asarray(roughness_um, float)
        self.grain_mm = np.ones(n) if grain_mm is None else np.asarray(grain_mm, float)
        self.albedo_texture = np.zeros(n) if albedo_texture is None else np.asarray(albedo_texture, float)
        self._caster = RayCaster(self.vertices, self.faces, what="scene")
        self.face_normals = self._caster.face_normals
        self.scale_mm = float(np.linalg.norm(self.vertices.max(axis=0) - self.vertices.min(axis=0)))

    @classmethod
    def from_meshes(
        cls, part_W: trimesh.Trimesh | None, sim: SimConfig, part_material: MaterialConfig | None = None
    ) -> Scene:
        """The table (a square of ``sim.table_size_mm`` on z=0 of {W}, centred on the origin) plus the part
        mesh, already placed in world coordinates (mm). ``part_material`` overrides ``sim.part_material``."""
        h = sim.table_size_mm / 2
        verts = [np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], dtype=np.float64)]
        faces = [np.array([[0, 1, 2], [0, 2, 3]])]
        mats = [sim.table_material] * 2
        part = [False, False]
        if part_W is not None and len(part_W.faces):
            mat = part_material or sim.part_material
            verts.append(np.asarray(part_W.vertices, dtype=np.float64))
            faces.append(np.asarray(part_W.faces) + 4)
            mats += [mat] * len(part_W.faces)
            part += [True] * len(part_W.faces)
        return cls(
            np.vstack(verts),
            np.vstack(faces),
            np.array(part),
            np.array([m.albedo for m in mats]),
            np.array([m.specular for m in mats]),
            np.array([m.shininess for m in mats]),
            np.array([m.roughness_um for m in mats]),
            np.array([m.grain_mm for m in mats]),
            np.array([m.albedo_texture for m in mats]),
        )

    def cast(self, origins: NDArray[np.float64], dirs: NDArray[np.float64]) -> Hits:
        """First hit of rays (N, 3) from ``origins`` along unit ``dirs`` (world mm)."""
        tri, distance, _, dirs = self._caster.first_hits(origins, dirs)
        hit = tri >= 0
        normal = np.full((len(dirs), 3), np.nan)
        n = self.face_normals[tri[hit]]
        facing_away = np.einsum("ij,ij->i", dirs[hit], n) > 0
        normal[hit] = np.where(facing_away[:, None], -n, n)
        return Hits(distance, tri, normal, hit & self.is_part[np.maximum(tri, 0)])

    def occluded(
        self, origins: NDArray[np.float64], dirs: NDArray[np.float64], max_distance: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """True where something lies on the ray closer than ``max_distance`` (mm): the shadow test."""
        return self._caster.occluded(origins, dirs, max_distance)
