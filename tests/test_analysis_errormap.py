"""Error map: signed point-to-triangle distance against independent references (trimesh brute force, SDF)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.errors import ConfigError


def _brute_force_signed(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Distance to every triangle (trimesh's closest-point routine), sign from ray-based containment."""
    tris = mesh.triangles
    d = np.empty(len(points))
    for i, p in enumerate(points):
        q = trimesh.triangles.closest_point(tris, np.repeat(p[None], len(tris), 0))
        d[i] = np.sqrt(((q - p) ** 2).sum(1)).min()
    inside = mesh.contains(points)
    return np.where(inside, -d, d)


def test_deformed_mesh_samples_match_exact_signed_distance() -> None:
    nominal = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    # The "manufactured" part: the nominal with a smooth bump/dent field (up to +-0.8 mm) and a shift.
    v = nominal.vertices
    radial = 0.8 * np.sin(v[:, 0] / 6.0) * np.cos(v[:, 1] / 7.0)
    actual = trimesh.Trimesh(v * (1 + radial[:, None] / 20.0) + [0.05, -0.03, 0.0], nominal.faces)
    pts, _ = trimesh.sample.sample_surface(actual, 400, seed=3)
    em = signed_distance(NominalMesh.from_trimesh(nominal), pts)
    ref = _brute_force_signed(nominal, pts)
    assert np.max(np.abs(em.deviation_mm - ref)) < 1e-3
    assert (em.deviation_mm > 0.05).any() and (em.deviation_mm < -0.05).any()  # both signs are exercised


def test_cube_edges_vertices_and_far_points_analytic() -> None:
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))  # centred at the origin
    rng = np.random.default_rng(7)
    pts = rng.uniform(-40, 40, (3000, 3))
    pts = np.vstack([pts, rng.uniform(-6, 6, (2000, 3)) * [1, 2, 3]])  # many inside and near edges/corners
    half = np.array([5.0, 10.0, 15.0])
    q = np.abs(pts) - half
    exact = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)  # box SDF
    em = signed_distance(NominalMesh.from_trimesh(box), pts)
    assert np.max(np.abs(em.deviation_mm - exact)) < 1e-9
    corner_region = (q > 0).sum(1) >= 2  # closest point on an edge or a vertex of the box
    assert corner_region.sum() > 1000
    assert set(np.unique(em.feature[corner_region])) <= {1, 2}


def test_degenerate_triangles_are_excluded_and_counted() -> None:
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    f = np.vstack([box.faces, [[0, 0, 1], [2, 2, 2]]])
    mesh = trimesh.Trimesh(box.vertices, f, process=False)
    nm = NominalMesh.from_trimesh(mesh)
    assert nm.excluded["degenerate_triangles"] == 2
    assert signed_distance(nm, [[0.0, 0.0, 8.0]]).deviation_mm[0] == pytest.approx(3.0)


def test_all_degenerate_mesh_is_a_config_error() -> None:
    mesh = trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False)
    with pytest.raises(ConfigError):
        NominalMesh.from_trimesh(mesh)
