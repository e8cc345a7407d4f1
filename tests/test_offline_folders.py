"""Capture folders: the manifest schema, bad input (one clear error naming the file, field or pose), and the
offline sensor calibration and scan on folders exported from the simulator (GCLS, images stored in a shuffled
order that the manifest lists). Truth: the simulated stage heights and the small sensor's baseline."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cell.calibration.capture_folder import load_capture_folder
from cell.cli import app
from cell.config import DEFAULT_CELL, load_cell_config
from cell.errors import CalibrationError, ConfigError
from cell.sensing.patterns import gcls_patterns, gcps_patterns
from fakes.sim.board import SteppedReferenceBoard
from fakes.sim.testing import BASELINE_MM, STANDOFF_MM, small_sensor

REAL = Path(__file__).parent / "data" / "procam_kamino410"


def _invoke(args: list[str]):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture()
def real_copy(tmp_path):
    return Path(shutil.copytree(REAL, tmp_path / "real"))


def _edit_manifest(folder: Path, **changes) -> None:
    m = yaml.safe_load((folder / "capture.yaml").read_text())
    m.update(changes)
    (folder / "capture.yaml").write_text(yaml.safe_dump(m))


# ----------------------------------------------------------------------------------------------- bad input
def test_missing_image_names_the_pose_and_frame(real_copy, tmp_path):
    (real_copy / "capture_2" / "graycode_41.png").unlink()
    res = _invoke(["calibrate", "projector", "--from", real_copy, "--out", tmp_path / "out"])
    assert isinstance(res.exception, ConfigError)
    msg = str(res.exception)
    assert "capture_2" in msg and "41 images" in msg and "needs 42" in msg and "'black'" in msg
    assert not (tmp_path / "out" / "projector.yaml").exists()


def test_image_of_another_size_names_the_file(real_copy, tmp_path):
    f = real_copy / "capture_1" / "graycode_07.png"
    cv2.imwrite(str(f), cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)[:-4])
    res = _invoke(["calibrate", "projector", "--from", real_copy, "--out", tmp_path / "out"])
    assert isinstance(res.exception, ConfigError)
    assert str(f) in str(res.exception) and "same size" in str(res.exception)


def test_colour_or_16_bit_image_for_an_8_bit_camera_names_the_file(real_copy):
    f = real_copy / "capture_0" / "graycode_03.png"
    cv2.imwrite(str(f), cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 256)
    folder = load_capture_folder(real_copy)
    with pytest.raises(ConfigError, match="uint16 image, a 8-bit camera") as exc:
        folder.stack(folder.poses[0])
    assert str(f) in str(exc.value)


def test_unknown_code_is_refused_naming_the_field(real_copy):
    _edit_manifest(real_copy, code={"kind": "phaseshift"})
    with pytest.raises(ConfigError, match="code.kind") as exc:
        load_capture_folder(real_copy)
    assert "capture.yaml" in str(exc.value)


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"code": {"kind": "gcls"}}, "code"),  # no stripe width
        ({"order": "opencv", "code": {"kind": "gcps", "stripe_px": 16}}, "order"),
        ({"order": ["white", "black"]}, "order"),
        ({"board": {"kind": "charuco", "squares": [10, 8], "square_mm": 75}}, "board"),
        ({"camera": {"width_px": 426}}, "camera.height_px"),
        ({"colour": "grey"}, "colour"),
    ],
)
def test_manifest_mistakes_name_the_field(real_copy, changes, field):
    _edit_manifest(real_copy, **changes)
    with pytest.raises(ConfigError, match=field):
        load_capture_folder(real_copy)


def test_pose_without_the_board_names_the_pose_and_file(real_copy, tmp_path):
    white = real_copy / "capture_3" / "graycode_40.png"
    img = cv2.imread(str(white), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(white), np.full_like(img, int(np.median(img))))
    res = _invoke(["calibrate", "intrinsics", "--from", real_copy, "--out", tmp_path / "out"])
    assert isinstance(res.exception, CalibrationError)
    assert "pose 'capture_3'" in str(res.exception) and str(white) in str(res.exception)
    assert not (tmp_path / "out" / "intrinsics.yaml").exists()


def test_capture_from_another_camera_is_refused_for_the_sensor_routine(tmp_path):
    res = _invoke(["calibrate", "sensor", "--from", REAL, "--cell", DEFAULT_CELL, "--out", tmp_path / "out"])
    assert isinstance(res.exception, ConfigError)
    assert "426x341" in str(res.exception) and "camera" in str(res.exception)


# --------------------------------------------------------------------------- simulator-exported folders
HEIGHTS_MM = (0.0, 4.0, 8.0, 12.0, 16.0, 20.0, 24.0)
PLANE_MM = 10.0


@pytest.fixture(scope="module")
def small_cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("cell")
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    sensor = small_sensor().model_dump(mode="json")
    sensor["T_T_C"] = data["sensor"]["T_T_C"]
    data["sensor"] = sensor
    (d / "small.yaml").write_text(yaml.safe_dump(data))
    return d / "small.yaml"


def _export(root: Path, cfg, heights, direction: str, shuffle: bool, seed: int) -> Path:
    """Board steps rendered by the simulator and written as a capture folder (16-bit PNG of 12-bit data,
    numbered without zero padding)."""
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    ps = gcls_patterns(proj.width_px, proj.height_px, 12, 6, direction)
    order = list(ps.names)
    if shuffle:
        order = [order[i] for i in np.random.default_rng(seed).permutation(len(order))]
    rig, rng = SteppedReferenceBoard(cfg.sensor, cfg.sim), np.random.default_rng(seed)
    poses = []
    for k, h in enumerate(heights):
        frames = rig.capture(h, ps.frames, rng)
        (root / f"step_{k:02d}").mkdir(parents=True)
        for i, name in enumerate(order):
            cv2.imwrite(str(root / f"step_{k:02d}" / f"img_{i}.png"), frames[ps.index(name)])
        poses.append({"dir": f"step_{k:02d}", "height_mm": h})
    manifest = {
        "camera": {"width_px": cam.width_px, "height_px": cam.height_px, "bit_depth": cam.bit_depth},
        "projector": {"width_px": proj.width_px, "height_px": proj.height_px},
        "code": {"kind": "gcls", "direction": direction, "stripe_px": 12, "n_shifts": 6},
        "order": order if shuffle else "cell",
        "poses": poses,
    }
    (root / "capture.yaml").write_text(yaml.safe_dump(manifest))
    return root


def test_offline_sensor_calibration_then_offline_scan_of_a_plane(tmp_path, small_cell):
    """`cell calibrate sensor --from` on exported steps (shuffled image order), then `cell scan --from` of a
    plane at 10 mm with that calibration: d = the small sensor's baseline, the plane at its stage height."""
    cfg = load_cell_config(small_cell)
    steps = _export(tmp_path / "steps", cfg, HEIGHTS_MM, "both", shuffle=True, seed=3)
    res = _invoke(
        [
            "calibrate",
            "sensor",
            "--from",
            steps,
            "--cell",
            small_cell,
            "--out",
            tmp_path / "cal",
            "--points",
            256,
        ]
    )
    assert res.exit_code == 0, (res.output, res.exception)
    report = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    assert report["summary"]["d_mm"]["mean"] == pytest.approx(BASELINE_MM, rel=0.03)
    assert report["summary"]["steps"] == len(HEIGHTS_MM)

    data = yaml.safe_load(small_cell.read_text())
    data["calibration"] = {"sensor": str(tmp_path / "cal" / "sensor.yaml")}
    calibrated = tmp_path / "calibrated.yaml"
    calibrated.write_text(yaml.safe_dump(data))
    plane = _export(tmp_path / "plane", cfg, (PLANE_MM,), "columns", shuffle=False, seed=4)
    res = _invoke(["scan", "--from", plane, "--cell", calibrated, "--out", tmp_path / "scan"])
    assert res.exit_code == 0, (res.output, res.exception)
    summary = json.loads((tmp_path / "scan" / "scan.json").read_text())
    assert "sensor.yaml" in summary["geometry_source"]
    assert summary["poses"]["step_00"]["points"] > 0.8 * 160 * 120
    import trimesh

    z = np.asarray(trimesh.load(tmp_path / "scan" / "step_00.ply").vertices)[:, 2]
    assert np.median(z) == pytest.approx(STANDOFF_MM - PLANE_MM, abs=0.05)
    assert np.std(z) < 0.1  # the small rig decodes to ~0.02 mm on a plane (docs/calibration.md)


def test_offline_projector_calibration_on_an_exported_charuco_gcps_folder(tmp_path):
    """A ChArUco board seen in 6 poses with GCPS in both directions (sim_binned.yaml: 512x384 camera, 1024x768
    projector), exported as a capture folder; `cell calibrate projector --from` recovers the projector that
    rendered it (sim_binned.yaml's, which the simulator renders with here)."""
    import trimesh

    from cell.calibration.handeye import pose_error
    from fakes.sim.board import board_poses, board_texture, charuco_board, render_textured_board_stack
    from fakes.sim.render import SceneRenderer
    from fakes.sim.scene import Scene

    cfg = load_cell_config(DEFAULT_CELL.parent / "sim_binned.yaml")
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    board = charuco_board((11, 8), 15.0, 11.0)
    tex, ppm = board_texture(board)
    renderer = SceneRenderer(cfg.sensor, cfg.sim, Scene.from_meshes(trimesh.creation.box((1, 1, 1)), cfg.sim))
    ps = gcps_patterns(proj.width_px, proj.height_px, 16, 4, "both")
    rng = np.random.default_rng(5)
    root = tmp_path / "charuco"
    for k, T in enumerate(board_poses(board, cfg.sensor.standoff_mm, 6, rng)):
        frames = render_textured_board_stack(renderer, T, tex, ppm, ps.frames, rng)
        (root / f"pose{k}").mkdir(parents=True)
        for i, f in enumerate(frames):
            cv2.imwrite(str(root / f"pose{k}" / f"{i:02d}.png"), f)
    manifest = {
        "camera": {"width_px": cam.width_px, "height_px": cam.height_px, "bit_depth": cam.bit_depth},
        "projector": {"width_px": proj.width_px, "height_px": proj.height_px},
        "code": {"kind": "gcps", "direction": "both", "stripe_px": 16, "n_phase": 4},
        "board": {"kind": "charuco", "squares": [11, 8], "square_mm": 15.0, "marker_mm": 11.0},
    }
    (root / "capture.yaml").write_text(yaml.safe_dump(manifest))
    res = _invoke(["calibrate", "projector", "--from", root, "--out", tmp_path / "p"])
    assert res.exit_code == 0, (res.output, res.exception)
    s = json.loads((tmp_path / "p" / "calibration.json").read_text())["summary"]
    assert s["views"] == 6 and s["stereo_rms_px"] < 0.1  # measured 0.069 px
    assert s["camera"]["K"][0][0] == pytest.approx(cam.fx_px, rel=5e-3)
    assert s["K"][0][0] == pytest.approx(proj.fx_px, rel=5e-3) and s["K"][1][1] == pytest.approx(
        proj.fy_px, rel=5e-3
    )
    dt, dr = pose_error(np.array(s["T_C_P"]), proj.T_C_P.matrix())
    assert dt < 1.5 and dr < 0.2, (dt, dr)  # measured 0.69 mm / 0.097 deg (camera fitted on the same 6 views)


# ------------------------------------------------------------------------------------------- plain Gray code
def test_plain_gray_code_is_opencvs_and_decodes_every_projector_pixel():
    """The frames equal OpenCV's GrayCodePattern.generate() in its order; seen pixel for pixel (camera =
    projector, 8-bit, with a dark level) they decode to each pixel's own column and row."""
    from cell.sensing.decode import decode
    from cell.sensing.graycode import graycode_patterns, opencv_order

    w, h = 100, 60
    ps = graycode_patterns(w, h)
    ok, generated = cv2.structured_light.GrayCodePattern.create(w, h).generate()
    order = opencv_order(ps)
    assert ok and len(generated) == len(order) - 2 and order[-2:] == ["white", "black"]
    for img, name in zip(generated, order, strict=False):
        assert np.array_equal(img, ps.frames[ps.index(name)]), name
    seen = (20 + ps.frames.astype(np.float32) * 0.6).astype(np.uint8)
    dec = decode(seen, ps, 8)
    yy, xx = np.mgrid[0:h, 0:w]
    assert np.array_equal(dec.axes["columns"].u, xx) and np.array_equal(dec.axes["rows"].u, yy)


def test_a_dark_coded_frame_names_its_file(real_copy):
    black = cv2.imread(str(real_copy / "capture_4" / "graycode_41.png"), cv2.IMREAD_UNCHANGED)
    f = (
        real_copy / "capture_4" / "graycode_00.png"
    )  # col_gray0 and its inverse: the projector was off for both
    cv2.imwrite(str(f), black)
    cv2.imwrite(str(real_copy / "capture_4" / "graycode_01.png"), black)
    folder = load_capture_folder(real_copy)
    with pytest.raises(ConfigError, match="all dark") as exc:
        folder.stack(folder.poses[4])
    assert str(f) in str(exc.value) and "col_gray0" in str(exc.value)


def test_a_missing_capture_folder_writes_nothing(tmp_path):
    res = _invoke(["calibrate", "intrinsics", "--from", tmp_path / "nowhere", "--out", tmp_path / "out"])
    assert isinstance(res.exception, ConfigError) and "capture folder not found" in str(res.exception)
    assert not (tmp_path / "out").exists()
