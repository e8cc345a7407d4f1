"""The cell's one ray caster (cell.raycast) on a box far from the origin: exact float64 hit points, misses,
and the planner's line-of-sight test built on it (cell.planning.occlusion)."""

from __future__ import annotations

import numpy as np
import trimesh

from cell.planning.occlusion import Occluder
from cell.raycast import RayCaster


def _box() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(20.0, 20.0, 10.0))  # top z = 5 before the shift
    box.apply_translation([1000.0, -700.0, 0.0])  # far from the origin, where float32 alone loses um
    return box


def test_first_hit_points_are_exact_and_misses_are_nan() -> None:
    box = _box()
    caster = RayCaster(box.vertices, box.faces)
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(991, 1009, 500), rng.uniform(-709, -691, 500)])
    origins = np.column_stack([xy, np.full(500, 400.0)])
    dirs = np.tile([0.0, 0.0, -1.0], (500, 1))
    dirs[-1] = [1.0, 0.0, 0.0]  # misses the box
    tri, points = caster.first_hit_points(origins, dirs)
    assert (tri[:-1] >= 0).all() and tri[-1] == -1 and np.isnan(points[-1]).all()
    assert np.abs(points[:-1, 2] - 5.0).max() < 1e-9 and np.allclose(points[:-1, :2], xy[:-1], atol=1e-9)
    assert np.allclose(box.face_normals[tri[:-1]], (0, 0, 1))


def test_occluder_sees_past_its_own_surface_not_through_the_part() -> None:
    box = _box()
    occ = Occluder(box)
    top = np.array([[1000.0, -700.0, 5.0], [1005.0, -705.0, 5.0]])
    up = np.tile([0.0, 0.0, 1.0], (2, 1))
    assert not occ.occluded(top, up, up, np.full(2, 300.0)).any()  # the top sees the sky
    beside = np.array([[1030.0, -700.0, 0.0]])  # 20 mm from the box's +x side, looking at it
    west = np.array([[-1.0, 0.0, 0.0]])
    assert occ.occluded(beside, -west, west, np.array([300.0])).all()
    assert not occ.occluded(beside, -west, west, np.array([15.0])).any()  # a segment that ends short of it
    assert occ.occluded(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)).shape == (0,)
