"""Triangulation against independent truth: eq 2.7 on synthetic steps, the simulator's hit points, the gauge
block's slot depths (recipes/parts/gauge.truth.json)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from scipy import stats

from cell.config import DEFAULT_CELL, SimConfig, load_cell_config
from cell.contracts import CameraSettings, PixelFormat
from cell.geometry import look_at, make_pose, transform_points
from cell.mesh import load_mesh
from cell.sensing.patterns import dissertation_gcls, gcls_patterns
from cell.sensing.scan import scan_view
from cell.sensing.triangulate import (
    PinholeTriangulator,
    ReferencePlaneTriangulator,
    Triangulator,
    fit_d_S,
    reference_model_from_geometry,
)
from fakes.camera import SimCamera
from fakes.clock import SimClock
from fakes.projector import SimProjector
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene
from fakes.sim.testing import BASELINE_MM, STANDOFF_MM, small_rig

PARTS = Path(__file__).resolve().parent.parent / "recipes" / "parts"


def test_fit_d_S_recovers_per_pixel_parameters_eq_2_7() -> None:
    rng = np.random.default_rng(0)
    d = rng.uniform(380, 450, (4, 5))
    S = rng.uniform(360, 420, (4, 5))
    h = np.array([-30.0, -10.0, 10.0, 25.0, 50.0])
    L = h[:, None, None] * d / (S - h[:, None, None])  # eq 2.1 solved for L
    d_fit, S_fit = fit_d_S(h, L)
    np.testing.assert_allclose(d_fit, d, rtol=1e-9)
    np.testing.assert_allclose(S_fit, S, rtol=1e-9)
    L[2, 0, 0] = np.nan  # a missing step still leaves four
    assert np.isfinite(fit_d_S(h, L)[0][0, 0])


def test_reference_model_from_geometry_recovers_the_prototype_baseline_and_standoff() -> None:
    sensor = load_cell_config(DEFAULT_CELL).sensor
    ref = reference_model_from_geometry(sensor)
    assert isinstance(ref, Triangulator)
    assert np.nanmax(np.abs(ref.d - 429.3)) < 0.02 and np.nanmax(np.abs(ref.S - sensor.standoff_mm)) < 0.02


@pytest.fixture(scope="module")
def plate_scan():
    tilt = make_pose(trimesh.transformations.rotation_matrix(0.2, [1, 0.3, 0])[:3, :3], [0, 0, 30.0])
    rig = small_rig(
        part_W=trimesh.creation.box((400, 300, 4), transform=tilt), bit_depth=8, sim=SimConfig(seed=11)
    )
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format=PixelFormat.MONO8))
    ps = gcls_patterns(128, 96, 8, 8)
    view = scan_view(rig.camera, rig.projector, ps, PinholeTriangulator.from_sensor(rig.sensor), bit_depth=8)
    return rig, view


def test_pinhole_cloud_matches_simulator_hit_points(plate_scan) -> None:
    rig, view = plate_scan
    gt = rig.renderer.ground_truth(rig.T_W_C).points_C
    ok = view.cloud.valid
    assert ok.mean() > 0.9 and np.all(np.isnan(view.cloud.points_C[~ok]))
    err = np.linalg.norm(view.cloud.points_C[ok] - gt[ok], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.1  # mm; ~1 mm camera pixels, 2 mm projector pixels


def test_reference_plane_model_agrees_with_pinhole(plate_scan) -> None:
    rig, view = plate_scan
    ref = reference_model_from_geometry(rig.sensor)
    assert isinstance(ref, ReferencePlaneTriangulator)
    c = ref.triangulate(view.decoded)
    diff = c.points_C[..., 2] - view.cloud.points_C[..., 2]
    assert np.nanmax(np.abs(diff)) < 0.002  # mm: both exact models of one geometry; float32 rounding + table


def test_depth_survives_the_d_S_ambiguity_of_a_noisy_eq_2_7_fit(plate_scan) -> None:
    """Eq 2.7 with 10 um of L noise per step: d and S move together by tenths of a mm, h barely moves, and
    the depth (taken from the reference plane, not from the fitted S) stays within the decoding noise."""
    rig, view = plate_scan
    ref = reference_model_from_geometry(rig.sensor)
    h = np.linspace(-50.0, 50.0, 11)  # the small sensor's depth of field is 100 mm
    L_true = BASELINE_MM * h / (STANDOFF_MM - h)  # eq 2.1: the small sensor's projector is at Z = 0 in {C}
    rng = np.random.default_rng(1)
    L = L_true[:, None, None] + rng.normal(0.0, 0.01, (len(h),) + ref.d.shape)
    d, S = fit_d_S(h, L)
    assert np.std(S - STANDOFF_MM) > 0.2 and np.std(d - BASELINE_MM) > 0.2  # mm: S alone is poorly fixed
    noisy = dataclasses.replace(ref, d=d, S=S).triangulate(view.decoded)
    Z_true = rig.renderer.ground_truth(rig.T_W_C).points_C[..., 2]
    ok = noisy.valid
    assert np.sqrt(np.mean((noisy.points_C[..., 2][ok] - Z_true[ok]) ** 2)) < 0.03  # mm


def _gauge_view(seed: int = 4):
    cfg = load_cell_config(DEFAULT_CELL)
    part = load_mesh(PARTS / "gauge.stl")
    renderer = SceneRenderer(cfg.sensor, cfg.sim, Scene.from_meshes(part, cfg.sim))
    T_W_C = look_at((0.0, 0.0, 30.0 + cfg.sensor.standoff_mm), (0.0, 0.0, 30.0), up=(0.0, 1.0, 0.0))
    projector = SimProjector(cfg.sensor.projector)
    camera = SimCamera(
        cfg.sensor.camera, renderer, projector, lambda: T_W_C, SimClock(), np.random.default_rng(seed)
    )
    projector.connect()
    projector.set_power(True)
    camera.connect()
    view = scan_view(
        camera, projector, dissertation_gcls(), PinholeTriangulator.from_sensor(cfg.sensor), bit_depth=8
    )
    return transform_points(T_W_C, view.cloud.points_C), view


@pytest.mark.skipif(not (PARTS / "gauge.stl").is_file(), reason="gauge block not built")
def test_gauge_block_slots_are_resolved() -> None:
    truth = json.loads((PARTS / "gauge.truth.json").read_text())
    P, _ = _gauge_view()
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    found = {}
    for slot in truth["slots"]:
        x0, x1 = slot["x_range_mm"]
        band = np.isfinite(z) & (np.abs(y) < 40)
        inside = band & (x > x0 + 1.5) & (x < x1 - 1.5)
        around = band & (((x > x0 - 8) & (x < x0 - 1.5)) | ((x > x1 + 1.5) & (x < x1 + 8)))
        depth_um = 1000 * (z[around].mean() - z[inside].mean())
        p = stats.ttest_ind(z[around], z[inside], equal_var=False, alternative="greater").pvalue
        found[slot["depth_um"]] = (depth_um, p)
    for nominal in (32.0, 24.0, 14.0):
        depth_um, p = found[nominal]
        assert p < 1e-6, (nominal, found)
        assert abs(depth_um - nominal) < 4.0, (nominal, found)
    print("gauge slots (nominal um: measured um, p):", found)


def _plane_columns(dist_proj: np.ndarray) -> tuple[PinholeTriangulator, object, np.ndarray]:
    """A plane 400 mm in front of the prototype sensor (camera 320x240, projector XGA at 429 mm, 47 deg):
    every pixel's true point, and the projector column a lens with ``dist_proj`` puts there (analytic)."""
    import cv2

    from cell.sensing.decode import AxisDecode, Decoded
    from cell.sensing.triangulate import normalized_coords

    K_cam = np.array([[630.0, 0, 159.5], [0, 630.0, 119.5], [0, 0, 1]])
    K_proj = np.array([[2600.0, 0, 511.5], [0, 2600.0, 383.5], [0, 0, 1]])
    T_C_P = make_pose(cv2.Rodrigues(np.array([0.0, -np.deg2rad(47.47), 0.0]))[0], [429.3, 0.0, 0.0])
    xn, yn = normalized_coords(K_cam, np.zeros(5), 320, 240)
    z = 400.0 + 0.05 * xn * 400.0  # a slightly tilted plane
    P_C = np.stack([xn * z, yn * z, z], axis=-1)
    P_P = transform_points(np.linalg.inv(T_C_P), P_C.reshape(-1, 3))
    uv, _ = cv2.projectPoints(P_P, np.zeros(3), np.zeros(3), K_proj, dist_proj)
    u = uv.reshape(240, 320, 2)[..., 0].astype(np.float32)
    ones = np.ones((240, 320), np.float32)
    decoded = Decoded(
        {"columns": AxisDecode("columns", u, np.zeros((240, 320), np.uint8), ones)}, ones, ones * 100
    )
    return PinholeTriangulator(K_cam, np.zeros(5), (320, 240), K_proj, T_C_P, dist_proj), decoded, P_C


def test_projector_lens_distortion_is_corrected_in_the_column_planes() -> None:
    """The world's projector lens (k1 -0.02, k2 0.01) bends the column planes: a pinhole model that ignores
    it puts the plane's points off by a tenth of a millimetre at the field's edge; with the lens (as
    `cell calibrate projector` measures it) they are back to the truth (analytic: float32 columns)."""
    lens = np.array([-0.02, 0.01, 0.0, 0.0, 0.0])
    tri, decoded, truth = _plane_columns(lens)
    corrected = tri.triangulate(decoded).points_C
    K_cam = np.array([[630.0, 0, 159.5], [0, 630.0, 119.5], [0, 0, 1]])
    ignored = PinholeTriangulator(K_cam, np.zeros(5), (320, 240), tri.K_proj, tri.T_C_P)
    ignored = ignored.triangulate(decoded).points_C
    err_ignored = np.linalg.norm(ignored - truth, axis=-1)
    err = np.linalg.norm(corrected - truth, axis=-1)
    assert np.nanmax(err_ignored) > 0.05  # the effect is real at this geometry
    assert np.nanmax(err) < 0.002  # float32 columns: ~1e-4 px


def test_the_compiled_lens_projection_is_opencvs() -> None:
    """The triangulator's own Brown-Conrady projection (no Jacobian: OpenCV's costs 15 doubles a coordinate)
    gives cv2.projectPoints' pixel to 1e-9 px, tangential terms and both axes included."""
    from cell.sensing._cloud_kernel import project_axis

    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-150, 150, (5000, 2)), rng.uniform(300, 700, 5000)])
    K = np.array([[1710.0, 0.0, 512.3], [0.0, 1705.0, 390.8], [0.0, 0.0, 1.0]])
    dist = np.array([-0.021, 0.013, 0.0011, -0.0007, 0.004])
    expected, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
    for axis in (0, 1):
        got = project_axis(P, K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist, axis)
        assert np.max(np.abs(got - expected.reshape(-1, 2)[:, axis])) < 1e-9
