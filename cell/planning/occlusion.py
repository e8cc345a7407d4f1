"""Line-of-sight tests from the part's surface against the part mesh (the shadow and hidden-point tests of
the sensor model), on the cell's one ray caster (:class:`cell.raycast.RayCaster`, Embree's any-hit query)."""

from __future__ import annotations

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.raycast import RayCaster

Array = NDArray[np.float64]

OFFSET_MM = 0.05  # rays start this far off the surface (along the normal) so they miss their own triangle


class Occluder:
    """Line-of-sight queries against one mesh in world coordinates (mm)."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        self.caster = RayCaster(np.asarray(mesh.vertices), np.asarray(mesh.faces), what="part mesh")

    def occluded(self, points: Array, normals: Array, dirs: Array, dist: Array) -> NDArray[np.bool_]:
        """True where the segment from each surface point (lifted along its normal) along unit ``dirs`` for
        ``dist`` mm hits the mesh."""
        return self.caster.occluded(
            points + OFFSET_MM * normals, dirs, np.maximum(np.asarray(dist) - OFFSET_MM, 0)
        )
