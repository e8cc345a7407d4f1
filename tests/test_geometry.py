"""Pose helpers against analytic rotations and the cell's frame conventions."""

from __future__ import annotations

import numpy as np
import pytest

from cell.geometry import (
    bounding_box,
    invert,
    look_at,
    pose_from_xyz_rotvec,
    pose_from_xyz_rpy,
    pose_to_xyz_rotvec,
    rotation_angle_between,
    transform_points,
)


def test_rpy_is_fixed_axis_xyz() -> None:
    # yaw 90 deg alone maps +x to +y; roll 90 deg alone maps +y to +z
    T = pose_from_xyz_rpy([1, 2, 3], [0, 0, np.pi / 2])
    np.testing.assert_allclose(transform_points(T, [1, 0, 0]), [1, 3, 3], atol=1e-12)
    T = pose_from_xyz_rpy([0, 0, 0], [np.pi / 2, 0, 0])
    np.testing.assert_allclose(transform_points(T, [0, 1, 0]), [0, 0, 1], atol=1e-12)


def test_invert_and_rotvec_round_trip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        xyz = rng.uniform(-500, 500, 3)
        rotvec = rng.uniform(-1, 1, 3)
        rotvec *= rng.uniform(0, np.pi - 1e-3) / np.linalg.norm(rotvec)
        T = pose_from_xyz_rotvec(xyz, rotvec)
        np.testing.assert_allclose(T @ invert(T), np.eye(4), atol=1e-12)
        np.testing.assert_allclose(pose_to_xyz_rotvec(T), np.concatenate([xyz, rotvec]), atol=1e-9)


def test_look_at_points_z_at_target_with_image_up() -> None:
    T = look_at([0, 0, 400], [0, 0, 0], up=[0, 1, 0])
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)  # optical axis down
    np.testing.assert_allclose(T[:3, 1], [0, -1, 0], atol=1e-12)  # image down (+y) is world -y
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    assert rotation_angle_between(T, T) == pytest.approx(0.0, abs=1e-12)


def test_bounding_box_is_the_min_and_max() -> None:
    """bounding_box: the corners numpy's min and max over axis 0 give, NaN propagated alike."""
    p = np.random.default_rng(2).normal(size=(1001, 3)) * 100
    lo, hi = bounding_box(p)
    assert np.array_equal(lo, p.min(0)) and np.array_equal(hi, p.max(0))
    p[5, 1] = np.nan
    assert np.array_equal(bounding_box(p)[0], p.min(0), equal_nan=True)
