"""The simulated cell's artefact stage: puts a verification artefact into the simulated scene.

The artefact is built from the certificate (exactly as certified) and lands where a technician's hand puts
it: the commanded pose followed by the world's placement error (fakes/sim/world.py; ideal world: exactly at
the command). The renderer's scene is rebuilt with the table and the artefact, in the certificate's matte
material; the robot is not told about the artefact (the verification poses keep the sensor far above it).
"""

from __future__ import annotations

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.verification.artefacts import ball_bar, plane, sphere_artefact
from cell.verification.certificate import Certificate
from cell.verification.stage import ArtefactName
from fakes.sim.scene import Scene
from fakes.sim.world import place_about
from fakes.sim_cell import SimCell


class SimArtefactStage:
    """Places certified artefacts in a :class:`SimCell`'s scene. ``placed_W`` is the true artefact pose
    (ground truth, for tests only)."""

    def __init__(self, sim: SimCell, certificate: Certificate):
        self.sim = sim
        self.certificate = certificate
        self.placed_W: NDArray[np.float64] | None = None

    def _mesh(self, artefact: ArtefactName) -> trimesh.Trimesh:
        c = self.certificate
        if artefact == "sphere":
            return sphere_artefact(c.sphere)
        if artefact == "plane":
            return plane(c.plane)
        bar = c.ball_bar if artefact == "ball_bar" else c.ball_bar_long
        if bar is None:
            raise ValueError(f"the certificate has no {artefact}")
        return ball_bar(bar)

    def _set_scene(self, mesh_W: trimesh.Trimesh | None) -> None:
        r = self.sim.renderer
        r.scene = Scene.from_meshes(mesh_W, self.sim.config.sim, self.certificate.material)
        r._cache.clear()  # cached view geometry belongs to the old scene
        self.sim.scene = r.scene

    def place(self, artefact: ArtefactName, T_W_A: NDArray[np.float64], label: str) -> None:
        T = np.asarray(T_W_A, dtype=np.float64)
        world = self.sim.world
        T_true = place_about(world.placement, T[:3, 3]) @ T if world is not None else T
        self._set_scene(self._mesh(artefact).apply_transform(T_true))
        self.placed_W = T_true

    def clear(self) -> None:
        self._set_scene(None)
        self.placed_W = None
