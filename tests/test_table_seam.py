"""The table at the part's foot, cropped in the aligned part frame (issue 17), against the simulator's truth.

One view of the box's -y wall and the table in front of it by the small simulated sensor. The cell believes
the view 0.9 mm higher than it is (a kinematic pose off by more than the table crop's 0.5 mm margin), so the
per-view crop in {W} keeps table points beside the wall's foot; the recipe's alignment puts the wall back
where it is, and there those table points lie on the table, off the part by up to the crop's 5 mm. The seam
crop in {P} must remove every one of them (the simulator says which pixels saw the table) and keep every
point the simulator puts on the wall above the margin.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from cell.analysis.crop import PartCrop
from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.table_seam import above_table_mm, table_seam
from cell.geometry import look_at, make_pose, transform_points
from cell.sensing.decode import decode
from cell.sensing.patterns import measuring_patterns
from cell.sensing.triangulate import PinholeTriangulator
from fakes.sim.testing import small_rig

LIFT_MM = 0.9  # the believed view pose sits this much above the true one
MARGIN_MM = 0.5  # the cell's table margin (InspectionSettings.table_margin_mm)


def test_seam_crop_removes_the_table_at_the_walls_foot_and_keeps_the_wall() -> None:
    # the part frame: the box of tests/box_part.py; placed in {W} turned 20 deg and moved, on the table
    box_P = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    box_P.apply_translation((0.0, 0.0, 20.0))
    T_W_P = make_pose(
        trimesh.transformations.rotation_matrix(math.radians(20), [0, 0, 1])[:3, :3], (15, -30, 0)
    )
    box_W = box_P.copy().apply_transform(T_W_P)
    wall_foot_W = transform_points(T_W_P, np.array([[0.0, -45.0, 8.0]]))[0]
    out_W = T_W_P[:3, :3] @ np.array([0.0, -1.0, 0.0])
    eye = wall_foot_W + 400.0 * (math.cos(math.radians(25)) * out_W + [0, 0, math.sin(math.radians(25))])
    pose = look_at(tuple(eye), tuple(wall_foot_W), up=(0.0, 0.0, 1.0))
    rig = small_rig(part_W=box_W, T_W_C=pose, bit_depth=8)
    cam, ps = rig.sensor.camera, measuring_patterns(rig.sensor.projector)
    stack = rig.renderer.render_stack(
        pose, list(ps.frames), cam.exposure_ms, cam.gain_db, np.random.default_rng(4), cam.bit_depth
    )
    gt = rig.renderer.ground_truth(pose)
    cloud = PinholeTriangulator.from_sensor(rig.sensor).triangulate(decode(stack, ps, cam.bit_depth))
    ok = cloud.valid & gt.hit
    believed = pose.copy()
    believed[2, 3] += LIFT_MM
    points_W = transform_points(believed, cloud.points_C[ok].astype(np.float64))
    on_part, true_W = gt.part[ok], gt.points_W[ok]

    # the per-view crop at the believed pose: table points beside the wall get through
    nominal_W = NominalMesh.from_trimesh(box_W)
    kept = (
        PartCrop(0.0, MARGIN_MM, 5.0).split(points_W, signed_distance(nominal_W, points_W).deviation_mm).part
    )
    table_through = kept & ~on_part
    assert table_through.sum() > 100, table_through.sum()  # the case arises (measured 285)

    # the alignment's correction (here the lift itself), into {P}; then the seam crop
    points_P = transform_points(np.linalg.inv(T_W_P), points_W[kept] - [0.0, 0.0, LIFT_MM])
    box = NominalMesh.from_trimesh(box_P)
    table = table_seam(points_P, T_W_P, MARGIN_MM, box)
    # the registration passes the deviations it has: the same cut
    deviation = signed_distance(box, points_P).deviation_mm
    np.testing.assert_array_equal(table_seam(points_P, T_W_P, MARGIN_MM, box, deviation_mm=deviation), table)
    survivors = np.flatnonzero(~table)
    cropped = points_P[survivors]

    # truth: no table point stays; every wall point the simulator puts above the margin (plus the noise) stays
    part_of_kept, true_z = on_part[kept], true_W[kept][:, 2]
    assert not (~part_of_kept[survivors]).any(), (~part_of_kept[survivors]).sum()
    wall = part_of_kept & (true_z > MARGIN_MM + 0.3)
    assert wall.sum() > 1000
    assert np.isin(np.flatnonzero(wall), survivors).all()
    # what stays at the foot (the lowest 2 mm) is on the part: within the sensor's noise of the true box
    foot = points_P[:, 2] < 2.0
    before = np.abs(signed_distance(box, points_P[foot]).deviation_mm)
    after = np.abs(signed_distance(box, cropped[cropped[:, 2] < 2.0]).deviation_mm)
    assert before.max() > 1.0  # the table points were gross errors of the cloud (measured 4.8 mm)
    assert after.max() < 0.3, after.max()  # measured 0.19 mm


def test_height_above_the_table_is_world_z() -> None:
    """``above_table_mm`` is the point's z in {W} (the table top z = 0) for any placement."""
    rng = np.random.default_rng(2)
    T = make_pose(trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3], rng.normal(0, 50, 3))
    p = rng.normal(0, 100, (50, 3))
    np.testing.assert_allclose(above_table_mm(p, T), transform_points(T, p)[:, 2], atol=1e-9)
