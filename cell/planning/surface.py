"""The nominal part surface the planner reasons about: area-weighted samples with normals, and which of them
are inspectable at all.

Samples (not triangles) carry coverage, so planning cost does not grow with the CAD's triangle count. A sample
is *inspectable* when some direction within theta_th2 of its normal that points up from the table (z >= 0.1)
reaches it unoccluded from the stand-off distance: faces lying on the table, the inside of a closed hat
section and undercuts are not, and coverage is reported over the inspectable area only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.planning.occlusion import Occluder

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PartSurface:
    """Mesh (world mm), its occluder, and N surface samples: points, unit normals, face, area share (mm^2)."""

    mesh: trimesh.Trimesh
    occluder: Occluder
    points: Array
    normals: Array
    face: NDArray[np.int64]
    area: Array
    inspectable: NDArray[np.bool_]

    @property
    def inspectable_area_mm2(self) -> float:
        return float(self.area[self.inspectable].sum())


def sample_surface(
    mesh: trimesh.Trimesh, count: int, seed: int, standoff_mm: float, max_view_angle_rad: float
) -> PartSurface:
    """Sample ``count`` points evenly by area (trimesh, seeded) and mark the inspectable ones."""
    points, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    points = np.array(points, dtype=np.float64)  # plain arrays: trimesh's tracked arrays are slow to slice
    normals = np.array(mesh.face_normals, dtype=np.float64)[face]
    area = np.full(len(points), float(mesh.area) / len(points))
    occ = Occluder(mesh)
    return PartSurface(
        mesh,
        occ,
        points,
        normals,
        np.asarray(face, dtype=np.int64),
        area,
        inspectable_mask(occ, points, normals, standoff_mm, max_view_angle_rad),
    )


def inspectable_mask(
    occ: Occluder, points: Array, normals: Array, standoff_mm: float, max_view_angle_rad: float
) -> NDArray[np.bool_]:
    """Try view directions tilted from the normal toward world +z (0, 1/3 ... 1 of the allowed angle, and
    straight up): inspectable if one of them is within the angle, points up and is unoccluded."""
    up = np.array([0.0, 0.0, 1.0])
    ok = np.zeros(len(points), dtype=bool)
    # rotation axis that tilts each normal toward +z
    axis = np.cross(normals, up)
    s = np.linalg.norm(axis, axis=1)
    axis = np.where(s[:, None] > 1e-9, axis / np.maximum(s, 1e-12)[:, None], np.array([1.0, 0.0, 0.0]))
    to_up = np.arccos(np.clip(normals[:, 2], -1, 1))
    for frac in (0.0, 1 / 3, 2 / 3, 1.0, None):
        ang = to_up if frac is None else np.minimum(frac * max_view_angle_rad, to_up)
        # Rodrigues: n rotated by ang about axis (axis is perpendicular to n)
        d = normals * np.cos(ang)[:, None] + np.cross(axis, normals) * np.sin(ang)[:, None]
        good = (
            (~ok)
            & (d[:, 2] >= 0.1)
            & (np.einsum("ij,ij->i", d, normals) >= np.cos(max_view_angle_rad) - 1e-9)
        )
        idx = np.flatnonzero(good)
        if len(idx):
            ok[idx[~occ.occluded(points[idx], normals[idx], d[idx], np.full(len(idx), standoff_mm))]] = True
    return ok
