"""Curvature labels (eqs 4.16-4.20), feature alignment and the weighted combination (eqs 4.21-4.22)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from cell.analysis.errormap import NominalMesh
from cell.analysis.features import Shape, curvature, feature_align, hk_labels
from cell.analysis.registration import combine_registrations, icp_point_to_plane
from cell.geometry import make_pose, pose_from_xyz_rpy, transform_points


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec())))


def test_curvature_of_sphere_and_cylinder_is_analytic() -> None:
    sphere = trimesh.creation.icosphere(4, radius=10.0)
    p, fi = trimesh.sample.sample_surface_even(sphere, 3000, seed=1)
    c = curvature(p, normals=sphere.face_normals[fi])
    assert np.median(c.K) == pytest.approx(1 / 100, rel=0.03)  # K = 1 / R^2
    assert np.median(c.H) == pytest.approx(-1 / 10, rel=0.03)  # H = -1 / R (outward normal, convex)
    assert np.mean(hk_labels(c, p) == Shape.PEAK) > 0.99
    cyl = trimesh.creation.cylinder(radius=8.0, height=120, sections=128)
    p, fi = trimesh.sample.sample_surface_even(cyl, 6000, seed=1)
    side = np.abs(p[:, 2]) < 50
    c = curvature(p, normals=cyl.face_normals[fi])
    assert np.median(np.abs(c.K[side])) < 1e-4 and np.median(c.H[side]) == pytest.approx(-1 / 16, rel=0.03)
    assert np.mean(hk_labels(c, p)[side] == Shape.RIDGE) > 0.95
    c_in = curvature(p, normals=-cyl.face_normals[fi])  # seen from inside, the same surface is a valley
    assert np.mean(hk_labels(c_in, p)[side] == Shape.VALLEY) > 0.95


def _embossed_sheet(n: int = 121) -> trimesh.Trimesh:
    """A 160 x 96 mm sheet with three embosses and a dimple at asymmetric places (a part with features)."""
    x, y = np.meshgrid(np.linspace(-80, 80, n), np.linspace(-48, 48, n))
    z = (
        6 * np.exp(-((x - 30) ** 2 + (y - 10) ** 2) / 60)
        + 4 * np.exp(-((x + 35) ** 2 + (y + 15) ** 2) / 40)
        - 5 * np.exp(-((x + 5) ** 2 + (y - 25) ** 2) / 50)
        + 3 * np.exp(-((x - 5) ** 2 + (y + 30) ** 2) / 30)
    )
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, 1:], i[1:, :-1]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(np.column_stack([x.ravel(), y.ravel(), z.ravel()]), f, process=False)


def test_feature_alignment_recovers_a_large_transform_then_icp_refines() -> None:
    part = _embossed_sheet()
    rng = np.random.default_rng(3)
    pts, _ = trimesh.sample.sample_surface(part, 15000, seed=3)
    pts = pts[pts[:, 0] > -70]  # the sensor saw most, not all, of the sheet
    T_cloud_P = pose_from_xyz_rpy([40.0, -25.0, 60.0], [0.4, -0.3, 1.1])  # 70 deg: far beyond ICP's reach
    cloud = transform_points(T_cloud_P, pts + rng.normal(0, 0.01, pts.shape))
    fa = feature_align(
        part, cloud, viewpoint_mm=transform_points(T_cloud_P, [0.0, 0.0, 300.0]), n_samples=15000
    )
    err = fa.T @ T_cloud_P  # identity when exact
    assert fa.n_matched >= 4
    assert _angle_deg(err) < 1.0 and np.linalg.norm(err[:3, 3]) < 1.0
    icp = icp_point_to_plane(NominalMesh.from_trimesh(part), cloud, T_init=fa.T)
    err = icp.T @ T_cloud_P
    assert _angle_deg(err) < 0.01 and np.linalg.norm(err[:3, 3]) < 0.01


def test_weighted_combination_of_rotations_and_translations() -> None:
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    Ta = make_pose(Rotation.from_rotvec(0.2 * axis).as_matrix(), [1.0, 0.0, 0.0])
    Tb = make_pose(Rotation.from_rotvec(0.6 * axis).as_matrix(), [0.0, 3.0, 0.0])
    c = np.array([10.0, -5.0, 2.0])
    T = combine_registrations([(Ta, 3.0), (Tb, 1.0)], c)
    assert np.allclose(Rotation.from_matrix(T[:3, :3]).as_rotvec(), 0.3 * axis, atol=1e-12)  # eq 4.21
    # The cloud centre lands on the weighted mean of where the two estimates put it.
    assert np.allclose(
        transform_points(T, c), 0.75 * transform_points(Ta, c) + 0.25 * transform_points(Tb, c)
    )
    assert np.allclose(combine_registrations([(Ta, 1.0), (Tb, 0.0)], c), Ta)
    # Rotations near +-pi combine without the wrap of raw rotation vectors.
    z = np.array([0.0, 0.0, 1.0])
    Tp = [make_pose(Rotation.from_rotvec(s * z).as_matrix()) for s in (np.pi - 0.1, -np.pi + 0.1)]
    Tw = combine_registrations([(Tp[0], 1.0), (Tp[1], 1.0)], np.zeros(3))
    assert _angle_deg(Tw) == pytest.approx(180.0, abs=1e-9)


def test_eq_4_22_angle_from_mean_normals() -> None:
    axis = np.array([0.0, 0.6, 0.8])
    R_true = Rotation.from_rotvec(0.5 * axis).as_matrix()
    n_cloud = np.array([0.3, -0.2, 0.93])
    n_nominal = R_true @ n_cloud
    # Both estimates share the true axis but their weighted angle (0.35 rad) is off; 4.22 restores 0.5.
    Ts = [make_pose(Rotation.from_rotvec(t * axis).as_matrix()) for t in (0.3, 0.4)]
    T = combine_registrations([(Ts[0], 1.0), (Ts[1], 1.0)], np.zeros(3), n_nominal, n_cloud)
    assert np.allclose(T[:3, :3], R_true, atol=1e-12)
    # Normals along the axis do not constrain the angle: the weighted one stays.
    T2 = combine_registrations([(Ts[0], 1.0), (Ts[1], 1.0)], np.zeros(3), axis, axis)
    assert np.allclose(Rotation.from_matrix(T2[:3, :3]).as_rotvec(), 0.35 * axis, atol=1e-12)
