"""Meshes of the verification artefacts, each in its own frame {A} (mm), from the certificate's values.

- sphere: centred on the origin.
- ball bar: sphere centres at x = -L/2 and x = +L/2, the bar along x between them.
- plane: the measured face is z = 0, centred on the origin, length along x, width along y; the body below.

They are the artefacts' CAD: the simulator renders them (fakes/artefact_stage.py) and make_artefacts.py writes
them for viewing. A sphere is an icosphere of 6 subdivisions whose surface's least-squares sphere has the
certified diameter, its facets within +-0.6 um of it (:func:`cell.calibration.validation.sphere_mesh_lsq`).
"""

from __future__ import annotations

import numpy as np
import trimesh

from cell.calibration.validation import sphere_mesh_lsq
from cell.verification.certificate import BallBarArtefact, PlaneArtefact, SphereArtefact

SPHERE_SUBDIVISIONS = 6


def sphere_mesh(diameter_mm: float) -> trimesh.Trimesh:
    """A closed sphere centred on the origin whose surface's least-squares sphere has ``diameter_mm`` (mm)."""
    return sphere_mesh_lsq(diameter_mm / 2, SPHERE_SUBDIVISIONS)


def sphere_artefact(a: SphereArtefact) -> trimesh.Trimesh:
    return sphere_mesh(a.diameter_mm)


def ball_bar(a: BallBarArtefact) -> trimesh.Trimesh:
    """Two spheres joined by a bar that ends inside each sphere (so no gap shows)."""
    L = a.centre_distance_mm
    d1, d2 = a.sphere_diameters_mm
    s1 = sphere_mesh(d1).apply_translation((-L / 2, 0, 0))
    s2 = sphere_mesh(d2).apply_translation((L / 2, 0, 0))
    bar_len = L - (d1 + d2) / 4  # from half-way inside one sphere to half-way inside the other
    bar = trimesh.creation.cylinder(radius=a.bar_diameter_mm / 2, height=bar_len, sections=48)
    bar.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    bar.apply_translation(((d1 - d2) / 8, 0, 0))
    joined = trimesh.util.concatenate([s1, s2, bar])
    assert isinstance(joined, trimesh.Trimesh)  # meshes concatenate to a mesh
    return joined


def plane(a: PlaneArtefact) -> trimesh.Trimesh:
    """A box whose top face (the measured face) is z = 0."""
    box = trimesh.creation.box(extents=(a.length_mm, a.width_mm, a.thickness_mm))
    return box.apply_translation((0, 0, -a.thickness_mm / 2))
