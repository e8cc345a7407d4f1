"""Renderer geometry against analytic truth: ray/plane hit points, projector coordinates, projections."""

from __future__ import annotations

import cv2
import numpy as np
import trimesh

from cell.geometry import invert, look_at, make_pose, transform_points
from fakes.sim.optics import pixel_rays, project_points
from fakes.sim.testing import small_rig

POSE = look_at((40.0, -30.0, 420.0), (10.0, 20.0, 0.0), up=(0.0, 1.0, 0.0))  # oblique view of the table


def _analytic_table_hits(sensor, T_W_C):
    """Pixel-centre rays of an undistorted pinhole intersected with z=0 of {W}, by hand."""
    cam = sensor.camera
    u, v = np.meshgrid(np.arange(cam.width_px, dtype=float), np.arange(cam.height_px, dtype=float))
    d_C = np.stack([(u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px, np.ones_like(u)], axis=-1)
    d_W = d_C @ T_W_C[:3, :3].T
    C = T_W_C[:3, 3]
    t = -C[2] / d_W[..., 2]
    return C + t[..., None] * d_W


def test_table_hits_match_analytic_ray_plane_intersection() -> None:
    rig = small_rig(distortion={}, T_W_C=POSE)
    gt = rig.renderer.ground_truth(POSE)
    expected = _analytic_table_hits(rig.sensor, POSE)
    assert gt.hit.all() and not gt.part.any()
    assert np.abs(gt.points_W - expected).max() < 1e-6
    np.testing.assert_allclose(gt.points_C, transform_points(invert(POSE), expected), atol=1e-6)
    np.testing.assert_allclose(gt.normals_W, np.broadcast_to([0.0, 0.0, 1.0], gt.normals_W.shape), atol=1e-12)


def test_distorted_rays_reproject_to_their_pixel_and_hit_the_plane() -> None:
    rig = small_rig(T_W_C=POSE)  # k1=-0.05, k2=0.02, p1=1e-4
    cam = rig.sensor.camera
    gt = rig.renderer.ground_truth(POSE)
    assert np.abs(gt.points_W[..., 2]).max() < 1e-6
    uv, _ = cv2.projectPoints(
        gt.points_C.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K(), cam.distortion.as_array()
    )
    u, v = np.meshgrid(np.arange(cam.width_px), np.arange(cam.height_px))
    pix = np.stack([u, v], axis=-1).reshape(-1, 2)
    assert np.abs(uv.reshape(-1, 2) - pix).max() < 1e-6


def test_tilted_part_plane_hits_and_part_mask() -> None:
    n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    p0 = np.array([0.0, 0.0, 60.0])
    R = trimesh.geometry.align_vectors([0, 0, 1], n)[:3, :3]
    plate = trimesh.creation.box((80.0, 60.0, 1e-3))  # a thin plate; the top face is what the camera sees
    plate.apply_transform(make_pose(R, p0 - n * 5e-4))
    rig = small_rig(part_W=plate, T_W_C=POSE)
    gt = rig.renderer.ground_truth(POSE)
    on_part = gt.part
    assert 1000 < on_part.sum() < on_part.size
    rays_W = pixel_rays(rig.sensor.camera) @ POSE[:3, :3].T
    C = POSE[:3, 3]
    t = np.dot(p0 - C, n) / (rays_W @ n)
    expected = C + t[..., None] * rays_W
    assert np.abs(gt.points_W[on_part] - expected[on_part]).max() < 1e-6
    np.testing.assert_allclose(gt.normals_W[on_part], np.broadcast_to(n, (on_part.sum(), 3)), atol=1e-9)


def test_projector_coordinates_match_analytic_projection() -> None:
    rig = small_rig(distortion={}, T_W_C=POSE)
    gt = rig.renderer.ground_truth(POSE)
    proj = rig.sensor.projector
    P_P = transform_points(invert(POSE @ proj.T_C_P.matrix()), _analytic_table_hits(rig.sensor, POSE))
    uv = np.stack(
        [
            proj.fx_px * P_P[..., 0] / P_P[..., 2] + proj.cx_px,
            proj.fy_px * P_P[..., 1] / P_P[..., 2] + proj.cy_px,
        ],
        axis=-1,
    )
    inside = ~np.isnan(gt.projector_uv[..., 0])
    assert inside.sum() > 0.5 * inside.size
    assert np.abs(gt.projector_uv[inside] - uv[inside]).max() < 0.01
    expected_inside = (
        (uv[..., 0] > -0.5)
        & (uv[..., 0] < proj.width_px - 0.5)
        & (uv[..., 1] > -0.5)
        & (uv[..., 1] < proj.height_px - 0.5)
    )
    assert np.array_equal(inside, expected_inside)


def test_project_points_matches_opencv_and_marks_points_behind() -> None:
    rig = small_rig()
    cam = rig.sensor.camera
    pts = np.random.default_rng(3).uniform([-50, -40, 300], [50, 40, 500], size=(200, 3))
    ref, _ = cv2.projectPoints(
        pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K(), cam.distortion.as_array()
    )
    np.testing.assert_allclose(project_points(cam, pts), ref.reshape(-1, 2), atol=1e-9)
    assert np.isnan(project_points(cam, np.array([[0.0, 0.0, -1.0]]))).all()
