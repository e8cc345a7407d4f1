"""Offset angle alpha (dissertation eqs 2.9-2.12) against simulator truth: a sensor whose projector sits off
the camera's row direction and is rotated about its optical axis so that its stripes run along the camera
columns, i.e. the stripes are not perpendicular to the baseline (Fig 2.10)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from cell.config import SimConfig
from cell.contracts import CameraSettings, PixelFormat
from cell.geometry import look_at, make_pose
from cell.sensing.patterns import gcls_patterns
from cell.sensing.scan import scan_view
from cell.sensing.triangulate import PinholeTriangulator, reference_model_from_geometry
from fakes.sim.testing import BASELINE_MM, STANDOFF_MM, small_rig

BETA = math.radians(10.0)  # baseline direction against the camera rows


def offset_projector(beta: float) -> dict:
    """Projector override for small_sensor: centre at BASELINE_MM in direction beta from the camera x axis,
    aimed at the camera axis at the stand-off, its y axis in the plane of the camera's y axis (so its columns
    project along the camera columns): relative to a projector squared on its baseline, rotated by ~beta about
    its optical axis."""
    P0 = BASELINE_MM * np.array([math.cos(beta), math.sin(beta), 0.0])
    T = look_at(P0, (0.0, 0.0, STANDOFF_MM), up=(0.0, -1.0, 0.0))
    rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
    return {"T_C_P": {"xyz_mm": P0.tolist(), "rpy_deg": rpy.tolist()}}


@pytest.fixture(scope="module")
def offset_scan():
    tilt = make_pose(trimesh.transformations.rotation_matrix(0.2, [1, 0.3, 0])[:3, :3], [0, 0, 30.0])
    rig = small_rig(
        part_W=trimesh.creation.box((400, 300, 4), transform=tilt),
        bit_depth=8,
        sim=SimConfig(seed=11),
        projector=offset_projector(BETA),
    )
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format=PixelFormat.MONO8))
    view = scan_view(
        rig.camera,
        rig.projector,
        gcls_patterns(128, 96, 8, 8),
        PinholeTriangulator.from_sensor(rig.sensor),
        bit_depth=8,
    )
    return rig, view, reference_model_from_geometry(rig.sensor)


def test_offset_angle_from_geometry_is_the_built_in_angle(offset_scan) -> None:
    _, _, ref = offset_scan
    assert abs(np.degrees(np.median(ref.alpha)) - 10.0) < 0.1  # centre columns run exactly along camera y
    assert np.ptp(np.degrees(ref.alpha)) < 3.0  # keystone of the tilted projector varies it a little
    np.testing.assert_allclose(ref.d, BASELINE_MM, atol=1e-6)  # eq 2.1 holds exactly with the true L'
    np.testing.assert_allclose(ref.S, STANDOFF_MM, atol=1e-6)


def test_alpha_correction_recovers_heights_and_its_absence_gives_eq_2_12_error(offset_scan) -> None:
    rig, view, ref = offset_scan
    Z_true = rig.renderer.ground_truth(rig.T_W_C).points_C[..., 2]
    corrected = ref.triangulate(view.decoded)
    raw = dataclasses.replace(ref, alpha=np.zeros_like(ref.alpha)).triangulate(view.decoded)
    ok = corrected.valid & raw.valid
    assert ok.mean() > 0.9
    err = corrected.points_C[..., 2][ok] - Z_true[ok]
    assert np.sqrt(np.mean(err**2)) < 0.06 and abs(err.mean()) < 0.05, (err.mean(), err.std())  # mm
    # Eq 2.12 with the nominal geometry: true L' = d h / (S - h) (eq 2.1), uncorrected L = L' cos(alpha);
    # the uncorrected height is low by dh, so Z = S - h is high by dh.
    h = STANDOFF_MM - Z_true[ok]
    Lp = BASELINE_MM * h / (STANDOFF_MM - h)
    L = Lp * np.cos(ref.alpha[ok])
    dh = Lp * STANDOFF_MM / (BASELINE_MM + Lp) - L * STANDOFF_MM / (BASELINE_MM + L)
    assert dh.mean() > 0.3  # the error is large against the ~0.02 mm noise: the check can fail
    err_raw = raw.points_C[..., 2][ok] - Z_true[ok]
    assert abs(err_raw.mean() - dh.mean()) < 0.15 * dh.mean(), (err_raw.mean(), dh.mean())
    assert np.sqrt(np.mean((err_raw - dh) ** 2)) < 0.06
    assert np.corrcoef(err_raw, dh)[0, 1] > 0.9  # it grows with the height as eq 2.12 says
