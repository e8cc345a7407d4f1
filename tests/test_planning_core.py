"""Planner building blocks against independent truth: analytic geometry, brute force, the dissertation's
eqs."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from cell.config import DEFAULT_CELL, load_cell_config
from cell.geometry import make_pose, transform_points
from cell.planning.coverage import covered_by_views
from cell.planning.feedback import cost_q, rotate_about
from cell.planning.patches import cluster_patches
from cell.planning.sensor_model import SensorModel
from cell.planning.settings import PlanSettings
from cell.planning.tour import order_tour, pose_costs, tour_length

CFG = load_cell_config(DEFAULT_CELL)


def test_field_of_view_matches_the_cell_config():
    s = SensorModel.from_config(CFG, PlanSettings())
    w, h = s.fov_mm
    assert w == pytest.approx(1024 * 393.7 / 2017.0)  # ~200 x 150 mm (sim.yaml comment, Table 2.x)
    assert 195 < w < 205 and 145 < h < 155
    # projector aimed at the field centre: triangulation angle = atan(baseline / stand-off)
    assert np.rad2deg(s.triangulation_angle) == pytest.approx(np.rad2deg(np.arctan2(429.3, 393.7)), abs=0.01)


def test_measurable_on_a_plane_is_the_image_footprint():
    s = SensorModel.from_config(CFG, PlanSettings())
    T = s.pose(np.zeros(3), np.array([0, 0, -1.0]), 0.0)
    xs, ys = np.meshgrid(np.linspace(-150, 150, 61), np.linspace(-120, 120, 49))
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    nrm = np.tile([0, 0, 1.0], (len(pts), 1))
    ok = s.measurable(T, pts, nrm, None)
    # inside the camera's footprint (and lit: the projector's footprint is larger) <=> measured
    w, h = s.fov_mm
    inside = (np.abs(pts @ T[:3, 0]) < w / 2 - 1) & (np.abs(pts @ T[:3, 1]) < h / 2 - 1)
    border = (np.abs(np.abs(pts @ T[:3, 0]) - w / 2) < 1) | (np.abs(np.abs(pts @ T[:3, 1]) - h / 2) < 1)
    assert np.array_equal(ok[~border], inside[~border])


def test_cost_q_is_the_modulus_of_eq_3_22():
    assert cost_q(3.0, 4.0, 1.0) == pytest.approx(5.0)
    assert cost_q(3.0, 4.0, 2.0) == pytest.approx(np.hypot(6.0, 4.0))
    assert cost_q(7.0, 0.0, 1.0) == pytest.approx(7.0)  # eq 3.27: Q = u when the distance cost is zero


def test_two_opt_matches_brute_force_on_small_tours():
    rng = np.random.default_rng(3)
    for _ in range(5):
        pts = rng.uniform(-300, 300, (7, 3))
        poses = [np.eye(4) for _ in pts]
        for T, p in zip(poses, pts):
            T[:3, 3] = p
        cost = pose_costs(poses)
        got = tour_length(cost, order_tour(cost, 0))
        best = min(tour_length(cost, [0, *perm]) for perm in itertools.permutations(range(1, 7)))
        assert got <= 1.25 * best  # 2-opt is a local optimum, not the optimum: within 25% on these


def test_patches_of_a_box_are_its_faces():
    box = trimesh.creation.box((100, 80, 40))
    lab = cluster_patches(box, np.deg2rad(25))
    assert len(np.unique(lab)) == 6
    for k in np.unique(lab):  # eq 3.1: every triangle within the cone of its patch's mean normal
        n = box.face_normals[lab == k]
        assert np.all(n @ n.mean(axis=0) / np.linalg.norm(n.mean(axis=0)) > np.cos(np.deg2rad(25)))


def test_patch_cone_splits_a_cylinder_into_sectors():
    cyl = trimesh.creation.cylinder(radius=100, height=200, sections=72)
    side = np.abs(cyl.face_normals[:, 2]) < 0.5
    lab = cluster_patches(cyl, np.deg2rad(25), side)
    # each sector spans < 2 x 25 deg of the 360 deg side: at least 8 sectors
    assert len(np.unique(lab[side])) >= 8


def test_rotate_about_keeps_the_pivot():
    T = np.eye(4)
    T[:3, 3] = [0, 0, 400]
    p = np.array([10.0, 0, 0])
    R = rotate_about(T, p, np.array([0, 1.0, 0]), 0.3)
    assert np.linalg.norm(R[:3, 3] - p) == pytest.approx(np.linalg.norm(T[:3, 3] - p))


def test_coverage_by_views_counts_as_a_brute_force_count_of_all_their_points():
    """covered_by_views (each view's points in its own frame and KD-tree, at most the needed number counted
    per view) against the definition: a sample is covered when the points of all views, moved into the world,
    within the radius (a closed disc: points exactly at it count) number at least half of the density's."""
    rng = np.random.default_rng(5)
    samples = rng.uniform(0.0, 20.0, (400, 3)) * [1.0, 1.0, 0.0]
    samples[0] = 0.0
    density, radius = 0.5, 2.0  # need = ceil(0.5 * 0.5 * pi * 4) = 4 points
    views, world = [], []
    for v in range(3):
        turn = Rotation.from_rotvec([0.0, 0.0, 0.7 * v]).as_matrix()
        T = np.eye(4) if v == 0 else make_pose(turn, [10.0, 10.0 * v - 5.0, 0.0])
        local = rng.uniform(-12.0, 12.0, (60 + 30 * v, 3)) * [1.0, 1.0, 0.02] + [10.0 * (v == 0), 0.0, 0.0]
        local = local[np.linalg.norm(transform_points(T, local)[:, :2], axis=1) > 2.5]  # none near sample 0
        if v == 0:  # but four exactly at the radius (in the world as in the view's frame: T = 1)
            local = np.vstack([local, [[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, -2.0, 0.0]]])
        views.append((cKDTree(local), T))
        world.append(transform_points(T, local))
    surface = SimpleNamespace(points=samples)
    d = cdist(samples, np.vstack(world))
    truth = (d <= radius).sum(axis=1) >= 4
    assert truth[0] and 0.2 < truth.mean() < 0.8, truth.mean()
    assert np.array_equal(covered_by_views(surface, views, density, radius), truth)
    inspectable = rng.uniform(size=len(samples)) < 0.5
    assert np.array_equal(
        covered_by_views(surface, views, density, radius, samples=inspectable), truth & inspectable
    )
