"""The simulated back-imaging rig end to end through ``cell glass``, against the simulator's ground truth
(true pixel rays, true screen points of the top and bottom reflections) and the made pane's analytic shape
(recipes/glass/panes/pane_sag.truth.json).

Speed: the rig is rig_small.yaml (the test rig's cameras reading a central 512x384 region of interest) and
one ``cell glass`` run, shared by the module, renders every image the tests read.
"""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from cell.analysis.report import Tolerance, out_of_tolerance_regions
from cell.cli import app
from cell.exit_codes import ExitCode
from cell.glass.calibration import ViewVectorCalibration
from cell.glass.config import GlassSearchConfig, load_glass_recipe, load_glass_rig
from cell.glass.grabs import load_grab, save_grab
from cell.glass.inspect import find_markers, measure
from cell.glass.job import glass_link_radius_mm, grab_mean
from cell.glass.markers import detect_dots
from cell.glass.surface import SmoothSurface, unit
from cell.mesh import load_mesh
from fakes.glass_rig import SimGlassRig
from fakes.sim.glass import GlassScene, expose
from fakes.sim.glass_pane import sag_height, windshield_height

GLASS = Path(__file__).resolve().parent.parent / "recipes" / "glass"
RECIPE, RIG = GLASS / "pane.yaml", GLASS / "rig_small.yaml"
TRUTH = json.loads((GLASS / "panes" / "pane_sag.truth.json").read_text())
BASE = windshield_height(TRUTH["radius_x_mm"], TRUTH["radius_y_mm"])
SAG = sag_height(BASE, TRUTH["sag_depth_mm"], tuple(TRUTH["sag_centre_mm"]), TRUTH["sag_sigma_mm"])


def _cell_glass(*args: str):
    return CliRunner().invoke(app, ["glass", *args])


@pytest.fixture(scope="module")
def sag_run(tmp_path_factory):
    """One ``cell glass`` run of the sagged pane on the small rig: calibrates, grabs, measures, reports."""
    out = tmp_path_factory.mktemp("glass") / "sag"
    res = _cell_glass(str(RECIPE), "--cell", str(RIG), "--out", str(out))
    assert res.exit_code == ExitCode.FAIL, res.output  # the sag is out of the band (test_cli_reports_the_sag)
    return out


@pytest.fixture(scope="module")
def rig_data(sag_run):
    """The run's averaged images and calibrations, the rig config and the nominal CAD surface."""
    cfg = load_glass_rig(RIG)
    images = [load_grab(sag_run / "views", c.name) for c in cfg.cameras]
    cals = [ViewVectorCalibration.load(sag_run / "calibration", c.name) for c in cfg.cameras]
    cad = SmoothSurface(load_mesh(load_glass_recipe(RECIPE).part.cad))
    return cfg, images, cals, cad


def test_cli_reports_the_sag(sag_run):
    doc = json.loads((sag_run / "results" / "report.json").read_text())
    assert doc["verdict"] == "fail"  # the 0.8 mm sag is outside the +-0.3 mm band
    deepest = min(r["extreme_mm"] for r in doc["regions"])
    assert abs(-deepest - TRUTH["sag_depth_mm"]) <= 0.1 * TRUTH["sag_depth_mm"]  # sag depth within 10%
    assert doc["regions"][0]["kind"] == "dent"
    assert doc["n_points"] > 0.75 * doc["n_points_input"]
    for name in ("report.html", "report.json", "cloud.ply"):
        assert (sag_run / "results" / name).stat().st_size > 0
    assert not (sag_run / "results" / "deviations.csv").exists()  # the cloud is stored once, in cloud.ply
    # cloud.ply: every accepted point with its deviation and measured normal, close to the made pane's
    # true normal
    raw = (sag_run / "results" / "cloud.ply").read_bytes()
    head, body = raw.split(b"end_header\n")
    assert b"property double nx" in head
    xyz = [(k, "<f4") for k in ("x", "y", "z")]  # float32 coordinates (docs/storage.md)
    rec = np.frombuffer(body, dtype=[*xyz, ("d", "<f4"), *((k, "<f8") for k in ("nx", "ny", "nz"))])
    assert len(rec) == doc["n_points"]
    x, y, h = rec["x"], rec["y"], 1e-3
    n_true = unit(
        np.column_stack(
            [
                -(SAG(x + h, y) - SAG(x - h, y)) / (2 * h),
                -(SAG(x, y + h) - SAG(x, y - h)) / (2 * h),
                np.ones(len(x)),
            ]
        )
    )
    n = np.column_stack([rec["nx"], rec["ny"], rec["nz"]])
    assert np.median(np.linalg.norm(np.cross(n, n_true), axis=1)) < 100e-6  # rad


def test_cli_nominal_pane_passes_with_saved_calibration(sag_run, tmp_path):
    rec = yaml.safe_load(RECIPE.read_text())
    rec["rig"] = str(RIG)
    rec["part"] = {"cad": str(GLASS / "panes" / "pane_nominal.stl")}
    rec["calibration_dir"] = str(sag_run / "calibration")
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(rec))
    res = _cell_glass(str(tmp_path / "r.yaml"), "--out", str(tmp_path / "ok"), "--frames", "2")
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "ok" / "results" / "report.json").read_text())
    assert doc["verdict"] == "pass" and doc["n_points"] > 500
    assert "loaded from" in doc["metadata"]["calibration"]
    assert not (tmp_path / "ok" / "calibration").exists()


def test_cli_missing_mesh_is_a_config_error(tmp_path):
    rec = yaml.safe_load(RECIPE.read_text())
    rec["rig"] = str(RIG)
    rec["part"] = {"cad": "nowhere.stl"}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(rec))
    res = _cell_glass(str(tmp_path / "r.yaml"), "--out", str(tmp_path / "x"))
    assert res.exit_code != 0 and "nowhere.stl" in str(res.exception)


def test_view_vectors_match_true_pixel_rays(rig_data, tmp_path):
    cfg, _, cals, _ = rig_data
    cam, cal = cfg.cameras[0], cals[0]
    uv = np.random.default_rng(1).uniform([60, 60], [450, 320], (500, 2))
    o, d = cal.rays_at(uv)
    xy = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), cam.K(), cam.distortion.as_array(), None, None, None, (3, 30, 1e-15)
    ).reshape(-1, 2)
    T = cam.T_W_C.matrix()
    d_true = unit(np.column_stack([xy, np.ones(len(xy))]) @ T[:3, :3].T)
    ang = np.linalg.norm(np.cross(d, d_true), axis=1)
    assert np.median(ang) < 20e-6 and np.percentile(ang, 95) < 40e-6  # measured 10 and 19 urad
    # where the calibrated ray crosses z=0 (the pane) vs the true ray: micrometres
    p_cal = o + (-o[:, 2] / d[:, 2])[:, None] * d
    p_true = T[:3, 3] + (-T[2, 3] / d_true[:, 2])[:, None] * d_true
    assert np.percentile(np.linalg.norm(p_cal - p_true, axis=1), 95) < 0.01
    # saved, versioned, reloaded identical
    cal.save(tmp_path)
    path = cal.save(tmp_path)
    assert path.name == f"{cam.name}.v2.npz"
    again = ViewVectorCalibration.load(tmp_path, cam.name)
    assert np.allclose(again.rays_at(uv)[1], d, equal_nan=True)


def test_thick_glass_bottom_reflection_never_taken():
    cfg = load_glass_rig(RIG)
    cfg.glass.thickness_mm = 8.0
    cam = cfg.cameras[2]
    scene = GlassScene(cfg, load_mesh(GLASS / "panes" / "pane_nominal.stl"))
    truth = scene.trace(cam)
    img = expose(cam, scene.radiance(truth), np.random.default_rng(5))
    det = detect_dots(img, full_profile_px=GlassSearchConfig().centroid_profile_px)
    uv = det.centroids_px

    def at(m):
        return np.column_stack([map_coordinates(m[..., i], [uv[:, 1], uv[:, 0]], order=1) for i in range(2)])

    tree = cKDTree(cfg.screen.dots_mm())
    d_top = tree.query(at(truth.screen_top))[0]
    d_bot = tree.query(np.nan_to_num(at(truth.screen_bottom), nan=1e6))[0]
    assert len(det) > 200
    assert np.all(d_top < d_bot)  # every detection is a top-layer dot, none the bottom copy
    assert np.percentile(d_top, 95) < 0.25  # mm on the screen (~0.7 px)


def test_sag_recovered_feedback_and_rejection(rig_data):
    cfg, images, cals, cad = rig_data
    recipe = load_glass_recipe(RECIPE)
    screen = SimGlassRig(cfg, None).screen
    one = measure(images, cals, cad, screen, recipe.search, max_cameras=1)
    four = measure(images, cals, cad, screen, recipe.search, max_cameras=4)
    assert np.array_equal(one.dot, four.dot)  # the same markers, so the errors compare point by point
    err1 = one.points[:, 2] - SAG(one.points[:, 0], one.points[:, 1])
    err4 = four.points[:, 2] - SAG(four.points[:, 0], four.points[:, 1])
    acc = four.accepted
    assert not one.accepted.any()  # a single camera confirms nothing
    assert acc.sum() > 0.75 * len(acc)
    rms = np.sqrt(np.mean(err4[acc] ** 2))
    assert rms <= 0.05  # issue check: shape RMS against the actual surface
    assert np.max(np.abs(err4[acc])) < 0.25
    assert np.sqrt(np.mean(err4[~acc] ** 2)) > 4 * rms  # what the test rejects is the bad part
    assert rms < 0.2 * np.sqrt(np.mean(err1[acc] ** 2))  # feedback vs one camera on the same markers
    # the predicted depth uncertainty describes the actual error
    assert 0.6 < rms / np.median(four.depth_sigma_mm[acc]) < 2.0
    # sag depth: recovered deviation from the nominal at the sag centre vs the truth, within 10%
    dev = four.points[:, 2] - BASE(four.points[:, 0], four.points[:, 1])
    cx, cy = TRUTH["sag_centre_mm"]
    near = acc & (np.hypot(four.points[:, 0] - cx, four.points[:, 1] - cy) < 8)
    assert near.sum() >= 3
    assert abs(-np.median(dev[near]) - TRUTH["sag_depth_mm"]) < 0.1 * TRUTH["sag_depth_mm"]


def _true_layer(cfg, mesh, cam, uv):
    """Per centroid: nearest screen dot of the true top reflection, distance to it, that of the bottom."""
    truth = GlassScene(cfg, mesh).trace(cam)

    def at(m):
        return np.column_stack([map_coordinates(m[..., i], [uv[:, 1], uv[:, 0]], order=1) for i in range(2)])

    tree = cKDTree(cfg.screen.dots_mm())
    d_top, dot = tree.query(np.nan_to_num(at(truth.screen_top), nan=1e6))
    d_bot = tree.query(np.nan_to_num(at(truth.screen_bottom), nan=1e6))[0]
    return dot, d_top, d_bot


def test_clear_thick_glass_bottom_copy_rejected_geometrically(rig_data):
    """Clear 8 mm glass: the bottom copies are nearly as dark as the top dots, so the threshold is raised to
    detect both and only the geometric test (cell.glass.bottom) tells them apart."""
    cfg0, _, cals, cad = rig_data
    cfg = cfg0.model_copy(deep=True)
    cfg.glass.thickness_mm, cfg.glass.absorption_per_mm = 8.0, 0.0
    sag = load_mesh(GLASS / "panes" / "pane_sag.stl")
    rig = SimGlassRig(cfg, sag)
    rig.connect()
    images = grab_mean(rig, 4)
    search = load_glass_recipe(RECIPE).search.model_copy(
        update={"dark_fraction": 0.7, "pane_thickness_mm": 8.0}
    )
    cam = cfg.cameras[0]
    raw = detect_dots(images[0], dark_fraction=0.7, full_profile_px=1)
    _, d_top_raw, d_bot_raw = _true_layer(cfg, sag, cam, raw.centroids_px)
    assert np.sum(d_bot_raw < d_top_raw) > 0.3 * len(raw)  # the detector alone takes many bottom copies
    m = find_markers(images[0], cals[0], cad, rig.screen, search)
    ok = m.dot >= 0
    dot, d_top, d_bot = _true_layer(cfg, sag, cam, m.detections.centroids_px[ok])
    assert ok.sum() > 200  # 263: the sag moves some markers beyond the identification gate
    assert np.all(d_top < d_bot)  # the bottom reflection is never taken for the marker
    assert np.all(dot == m.dot[ok]) and np.percentile(d_top, 99) < 0.25  # right dot, unbiased centroid
    g = measure(images, cals, cad, rig.screen, search)
    err = g.points[:, 2] - SAG(g.points[:, 0], g.points[:, 1])
    assert g.accepted.sum() > 0.6 * len(err)  # 0.75: cam3 sees every dot merged with its copy, none used
    assert np.sqrt(np.mean(err[g.accepted] ** 2)) <= 0.05  # issue check on clear thick glass


@pytest.fixture(scope="module")
def second_screen(rig_data):
    """The sagged pane's frames with the screen moved to its second position: (first screen, (frames,
    second screen))."""
    rig = SimGlassRig(rig_data[0], load_mesh(GLASS / "panes" / "pane_sag.stl"))
    rig.connect()
    screen = rig.screen
    screen2 = rig.move_screen(1)  # move first, then grab
    return screen, (grab_mean(rig, 4), screen2)


def test_a_runs_grabs_come_back_bit_for_bit_and_smaller(sag_run, second_screen, tmp_path):
    """The rig's 8-bit cameras, 4 frames averaged: `cell glass` stores each mean as the 16-bit PNG of the
    frames' sum (cell/glass/grabs.py) and reads back the very float32 image the measurement read."""
    assert sorted(p.name for p in (sag_run / "views").iterdir()) == [
        "cam0.png",
        "cam1.png",
        "cam2.png",
        "cam3.png",
        "grabs.json",
    ]
    images = second_screen[1][0]  # the sagged pane's frames grabbed here
    for k, image in enumerate(images):
        assert save_grab(tmp_path, f"cam{k}", image, 4).suffix == ".png"
        back = load_grab(tmp_path, f"cam{k}")
        assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), image.view(np.uint32))
    png = sum((tmp_path / f"cam{k}.png").stat().st_size for k in range(len(images)))
    assert png < 0.5 * sum(image.nbytes for image in images)  # against the float32 .npy written before
    grabs = json.loads((tmp_path / "grabs.json").read_text())["grabs"]
    assert [g["frames"] for g in grabs.values()] == [4] * len(images)


def test_multi_projection_without_cad_normal(rig_data, second_screen):
    """Multi-projection (2.4) with the screen moved 60 mm: one camera, no feedback, no CAD-normal assumption,
    recovers the sag that the single-camera golden-section search cannot (depth-normal ambiguity)."""
    _, images, cals, cad = rig_data
    screen, second = second_screen
    search = load_glass_recipe(RECIPE).search
    golden = measure(images, cals, cad, screen, search, max_cameras=1)
    mp = measure(
        images,
        cals,
        cad,
        screen,
        search.model_copy(update={"method": "multi_projection"}),
        max_cameras=1,
        second=second,
    )
    assert len(mp.points) > 0.95 * len(golden.points)
    err_g = golden.points[:, 2] - SAG(golden.points[:, 0], golden.points[:, 1])
    err_m = mp.points[:, 2] - SAG(mp.points[:, 0], mp.points[:, 1])
    assert np.sqrt(np.mean(err_m**2)) <= 0.05  # measured 0.030 mm
    assert np.sqrt(np.mean(err_m**2)) < 0.1 * np.sqrt(np.mean(err_g**2))
    x, y, h = mp.points[:, 0], mp.points[:, 1], 1e-3
    n_true = unit(
        np.column_stack(
            [
                -(SAG(x + h, y) - SAG(x - h, y)) / (2 * h),
                -(SAG(x, y + h) - SAG(x, y - h)) / (2 * h),
                np.ones(len(x)),
            ]
        )
    )
    assert np.median(np.linalg.norm(np.cross(mp.normals, n_true), axis=1)) < 200e-6
    # No CAD normal assumed, so one camera's points are judged by their own two-screen fit, not left out as
    # golden-section single-camera points are: nearly all accepted, within the RMS, and the
    # predicted depth uncertainty describes the actual error.
    assert mp.single_projection.all() and not golden.accepted.any()
    acc = mp.accepted
    assert acc.sum() > 0.95 * len(acc)
    rms = np.sqrt(np.mean(err_m[acc] ** 2))
    assert rms <= 0.05
    assert 0.6 < rms / np.median(mp.depth_sigma_mm[acc]) < 2.0


def test_multi_projection_with_feedback_accepts_more_than_golden_section(rig_data, second_screen):
    """Four cameras: multi-projection keeps the points only one camera sees (pane edges, image corners),
    which golden section must leave unconfirmed; the accepted RMS stays within the issue's 0.05 mm."""
    _, images, cals, cad = rig_data
    screen, second = second_screen
    screen2 = second[1]
    search = load_glass_recipe(RECIPE).search
    golden = measure(images, cals, cad, screen, search, max_cameras=4)
    mp = measure(
        images, cals, cad, screen, search.model_copy(update={"method": "multi_projection"}), second=second
    )
    err = mp.points[:, 2] - SAG(mp.points[:, 0], mp.points[:, 1])
    assert mp.single_projection.any() and mp.accepted[mp.single_projection].mean() > 0.8
    assert mp.accepted.sum() > golden.accepted.sum() + 0.5 * mp.single_projection.sum()
    assert np.sqrt(np.mean(err[mp.accepted] ** 2)) <= 0.05
    single = mp.accepted & mp.single_projection
    assert np.sqrt(np.mean(err[single] ** 2)) <= 0.05
    # frames labelled with the wrong screen position (grabbed before the move): the fit refuses them
    wrong = measure(
        images,
        cals,
        cad,
        screen,
        search.model_copy(update={"method": "multi_projection"}),
        second=(images, screen2),
    )
    assert wrong.single_projection.sum() > 20 and wrong.accepted[wrong.single_projection].mean() < 0.1


def test_sag_is_one_region_with_a_marker_spaced_link_radius(sag_run):
    """Glass points are one per marker, so the report's default link radius (3x the median spacing of the
    merged cameras' clouds) splits the sag; linking at the marker spacing of one camera keeps it whole."""
    z = np.load(sag_run / "results" / "glass_points.npz")
    acc = z["accepted"]
    pts, dev = (
        z["points_W"][acc],
        z["points_W"][acc][:, 2] - BASE(z["points_W"][acc][:, 0], z["points_W"][acc][:, 1]),
    )
    radius = glass_link_radius_mm(z["points_W"], z["camera"])
    regions = out_of_tolerance_regions(pts, dev, Tolerance(-0.3, 0.3), link_radius_mm=radius)
    n_bad = int(np.sum(np.abs(dev) > 0.3))
    assert regions[0]["n_points"] >= 0.95 * n_bad and regions[0]["kind"] == "dent"  # the sag: one region
    assert abs(-regions[0]["extreme_mm"] - TRUTH["sag_depth_mm"]) < 0.1 * TRUTH["sag_depth_mm"]
