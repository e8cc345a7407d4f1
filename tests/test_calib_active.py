"""The active calibration (cell/calibration/active.py) on the simulated prototype: a cell config whose nominal
geometry is deliberately wrong (camera fx +1 %, projector 2 mm off along the baseline) plus the files that
`cell calibrate intrinsics` and `cell calibrate projector` write measure a plane rendered with the TRUE
geometry (recipes/cells/sim.yaml) far better than the wrong config alone."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from cell.calibration import active_sensor_config, active_triangulator, calibration_source
from cell.calibration.store import save_calibration
from cell.cli import main
from cell.config import DEFAULT_CELL, load_cell_config
from cell.errors import ConfigError
from cell.sensing.decode import decode
from cell.sensing.patterns import gcps_patterns
from fakes.sim.board import SteppedReferenceBoard

HEIGHT_MM = 25.0  # plane above the reference plane


@pytest.fixture(scope="module")
def configs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("active")
    # the prototype with world: ideal, so that its config is the truth the wrong config is compared with
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    data["world"] = "ideal"
    ideal = tmp / "ideal.yaml"
    ideal.write_text(yaml.safe_dump(data))
    main(["calibrate", "intrinsics", "--cell", str(ideal), "--out", str(tmp / "intr"), "--views", "8"])
    intr = tmp / "intr" / "intrinsics.yaml"
    main(
        ["calibrate", "projector", "--cell", str(ideal), "--out", str(tmp / "proj"), "--views", "6"]
        + ["--intrinsics", str(intr)]
    )
    data["sensor"]["camera"]["fx_px"] *= 1.01
    data["sensor"]["projector"]["T_C_P"]["xyz_mm"][0] += 2.0
    (tmp / "wrong.yaml").write_text(yaml.safe_dump(data))
    data["calibration"] = {"intrinsics": str(intr), "projector": str(tmp / "proj" / "projector.yaml")}
    (tmp / "calibrated.yaml").write_text(yaml.safe_dump(data))
    return load_cell_config(ideal), load_cell_config(tmp / "wrong.yaml"), tmp / "calibrated.yaml"


@pytest.mark.slow
def test_calibration_files_correct_a_wrong_config(configs):
    true, wrong, cal_path = configs
    cal = load_cell_config(cal_path)
    assert calibration_source(wrong) == "config geometry (no calibration)"
    src = calibration_source(cal)
    assert "intrinsics: intrinsics.yaml" in src and "projector: projector.yaml" in src
    s = active_sensor_config(cal)
    assert s.camera.fx_px == pytest.approx(true.sensor.camera.fx_px, rel=2e-3)
    assert np.linalg.norm(s.projector.T_C_P.matrix()[:3, 3] - true.sensor.projector.T_C_P.matrix()[:3, 3]) < 1
    assert cal.sensor.camera.fx_px == wrong.sensor.camera.fx_px  # the config itself is left as written

    rig = SteppedReferenceBoard(true.sensor, true.sim)
    proj = true.sensor.projector
    ps = gcps_patterns(proj.width_px, proj.height_px, 16, 4, "columns")
    dec = decode(
        rig.capture(HEIGHT_MM, ps.frames, np.random.default_rng(3)), ps, true.sensor.camera.bit_depth
    )
    rms = {}
    for name, cfg in (("wrong", wrong), ("calibrated", cal)):
        c = active_triangulator(cfg).triangulate(dec)
        e = c.points_C[c.valid][:, 2] - (true.sensor.standoff_mm - HEIGHT_MM)  # the plane's true depth
        rms[name] = float(np.sqrt(np.mean(e * e)))
    # measured: wrong 1.78 mm, calibrated 0.06 mm (the true geometry gives 0.021 mm on these images)
    assert rms["calibrated"] < 0.1 and rms["wrong"] > 10 * rms["calibrated"], rms


def test_calibration_for_another_device_is_refused(tmp_path):
    cam = load_cell_config(DEFAULT_CELL).sensor.camera
    arrays = {"K": cam.K(), "dist": np.zeros(5)}
    save_calibration(tmp_path / "intr", "camera_intrinsics", arrays, {"camera": {"serial": "OTHER-CAMERA"}})
    save_calibration(tmp_path / "he", "hand_eye", {"T_T_C": np.eye(4)}, {})
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    path = tmp_path / "cell.yaml"
    for files, message in (
        ({"intrinsics": "intr.yaml"}, "serial 'OTHER-CAMERA'"),
        ({"intrinsics": "he.yaml"}, "expected 'camera_intrinsics'"),
        ({"projector": "intr.yaml"}, "expected 'projector'"),
    ):
        data["calibration"] = files
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(ConfigError, match=message):
            active_triangulator(load_cell_config(path))


def test_the_projector_file_brings_the_camera_lens_it_was_adjusted_with(tmp_path):
    """cell calibrate projector adjusts both lenses together (cell/calibration/projector.py); its file holds
    the camera's, which then replaces the intrinsics file's: the transform is consistent with that camera
    only. A projector file without it (made before) leaves the intrinsics file's camera active."""
    cfg = load_cell_config(DEFAULT_CELL)
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    K_intr, K_joint = cam.K(), cam.K()
    K_intr[0, 0] += 3.0
    K_joint[0, 0] += 1.0
    devices = {
        "projector": {"serial": proj.serial, "resolution": [proj.width_px, proj.height_px]},
        "camera": {"serial": cam.serial, "resolution": [cam.width_px, cam.height_px]},
    }
    save_calibration(tmp_path / "intr", "camera_intrinsics", {"K": K_intr, "dist": np.zeros(5)}, {})
    base = {"K": proj.K(), "dist": np.zeros(5), "T_C_P": proj.T_C_P.matrix()}
    save_calibration(tmp_path / "old", "projector", base, {})
    save_calibration(
        tmp_path / "joint",
        "projector",
        {**base, "camera_K": K_joint, "camera_dist": np.full(5, 1e-4)},
        devices,
    )
    devices["camera"]["serial"] = "OTHER-CAMERA"
    save_calibration(
        tmp_path / "other", "projector", {**base, "camera_K": K_joint, "camera_dist": np.zeros(5)}, devices
    )
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    path = tmp_path / "cell.yaml"

    def active(projector: str):
        data["calibration"] = {"intrinsics": "intr.yaml", "projector": projector}
        path.write_text(yaml.safe_dump(data))
        c = load_cell_config(path)
        return active_sensor_config(c), calibration_source(c)

    s, src = active("old.yaml")
    assert s.camera.fx_px == K_intr[0, 0] and "refined with the projector" not in src
    s, src = active("joint.yaml")
    assert s.camera.fx_px == K_joint[0, 0] and s.camera.distortion.k1 == 1e-4
    assert "camera lens: as refined with the projector" in src
    with pytest.raises(ConfigError, match="serial 'OTHER-CAMERA'"):
        active("other.yaml")
