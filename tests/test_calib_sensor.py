"""Per-pixel sensor calibration (dissertation 2.2, 5.1.1) on the simulator, against analytic truth.

Truth: the board moves along the camera axis and the projector centre lies in the camera's z = 0 plane, so for
every pixel h = L'S/(d + L') holds exactly with S = the reference-plane depth (stand-off), d = the baseline
length and alpha = the angle of the baseline to the camera rows (the column stripes run along camera y on the
board, because the projector is turned about camera y only). Here the baseline is turned 3 deg out of the
rows.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cell.calibration.sensor import SensorCalibrator, load_sensor_model, save_sensor_calibration
from cell.calibration.validation import flat_test, sphere_test
from cell.config import SimConfig
from cell.errors import CalibrationError, ConfigError
from cell.geometry import transform_points
from cell.sensing.decode import decode
from cell.sensing.patterns import gcls_patterns
from cell.sensing.triangulate import PinholeTriangulator
from fakes.sim.board import SteppedReferenceBoard, sphere_on_board
from fakes.sim.testing import BASELINE_MM, STANDOFF_MM, small_sensor

BETA_DEG = 3.0


@pytest.fixture(scope="module")
def rig():
    b = math.radians(BETA_DEG)
    sensor = small_sensor(
        projector={
            "T_C_P": {
                "xyz_mm": [BASELINE_MM * math.cos(b), BASELINE_MM * math.sin(b), 0.0],
                "rpy_deg": [0.0, -math.degrees(math.atan2(BASELINE_MM, STANDOFF_MM)), 0.0],
            }
        }
    )
    return SteppedReferenceBoard(sensor, SimConfig(seed=7))


@pytest.fixture(scope="module")
def calibrated(rig):
    ps = gcls_patterns(128, 96, 8, 8, "both")
    cal = SensorCalibrator(rig.sensor.camera, rig.sensor.projector, rig.sensor.standoff_mm, n_points=1024)
    rng = np.random.default_rng(1)
    for k in range(31):  # the dissertation's 30 steps of 1 mm after the reference plane
        cal.add_step(float(k), decode(rig.capture(float(k), ps.frames, rng), ps, 12))
    return cal, cal.finish()


def test_recovers_d_S_alpha(calibrated):
    _, res = calibrated
    ok = np.isfinite(res.d_mm)
    assert ok.sum() > 900
    assert np.median(res.d_mm[ok]) == pytest.approx(BASELINE_MM, rel=0.01)
    assert np.median(res.S_mm[ok]) == pytest.approx(STANDOFF_MM, rel=0.01)
    assert np.degrees(np.median(res.alpha_rad[ok])) == pytest.approx(BETA_DEG, abs=0.1)
    assert np.median(res.residual_mm[ok]) < 0.01  # the model fits the 31 steps to ~5 um
    # the per-pixel maps cover the whole image
    assert np.all(np.isfinite(res.model.d)) and res.model.d.shape == (120, 160)


def test_flat_test_at_known_heights(rig, calibrated):
    _, res = calibrated
    ps = gcls_patterns(128, 96, 8, 8, "columns")
    rng = np.random.default_rng(9)
    for h in (12.5, 27.3):  # between the calibration steps
        f = flat_test(
            res.model.triangulate(decode(rig.capture(h, ps.frames, rng), ps, 12)), res.model.res_mm, h
        )
        assert abs(f["mean_mm"]) < 0.005 and f["std_mm"] < 0.03, f


def test_sphere_test(rig, calibrated):
    """A 50 mm ball on the reference board, measured with the calibrated per-pixel model and with the true
    geometry (pinhole, sim config) from the same decoded images: the calibration must add almost nothing to
    the decoding's own error on this small rig, and the fitted sphere must match the scene's."""
    _, res = calibrated
    ps = gcls_patterns(128, 96, 8, 8, "columns")
    cam = rig.sensor.camera
    ball, centre = sphere_on_board(25.0)
    images = rig.renderer(0.0, ball).render_stack(
        rig.T_W_C, list(ps.frames), cam.exposure_ms, cam.gain_db, np.random.default_rng(11)
    )
    dec = decode(images, ps, 12)
    out = {}
    for name, tri in (("model", res.model), ("truth", PinholeTriangulator.from_sensor(rig.sensor))):
        c = tri.triangulate(dec)
        out[name] = sphere_test(transform_points(rig.T_W_C, c.points_C[c.valid]), 25.0, centre)
    m, t = out["model"], out["truth"]
    assert m["points"] > 1500
    # radius error / fit residual / centre offset, measured: model -0.231 / 0.106 / 0.27 mm, true geometry
    # -0.243 / 0.106 / 0.29 mm (the full-resolution prototype decodes a 25 mm ball to -0.016 / 0.013 mm)
    assert abs(m["radius_error_mm"] - t["radius_error_mm"]) < 0.02, out
    assert m["std_mm"] < t["std_mm"] + 0.01 and m["centre_offset_mm"] < t["centre_offset_mm"] + 0.05, out
    assert abs(m["radius_error_mm"]) < 0.3 and m["std_mm"] < 0.13, out
    with pytest.raises(CalibrationError, match="sphere test"):
        sphere_test(transform_points(rig.T_W_C, c.points_C[c.valid]), 25.0, centre + (0, 0, 20))


def test_save_load_and_no_worse_overwrite(tmp_path, rig, calibrated):
    cal, res = calibrated
    cam, proj = rig.sensor.camera, rig.sensor.projector
    path = tmp_path / "sensor"
    save_sensor_calibration(res, path, cam, proj)
    assert (tmp_path / "sensor_d.png").exists() and (tmp_path / "sensor.npz").exists()
    model = load_sensor_model(path, cam)
    np.testing.assert_array_equal(model.d, res.model.d)
    worse = cal.finish(stride=4)  # 64 points: a coarser calibration
    worse.height_sigma_mm += 1.0
    with pytest.raises(CalibrationError, match="better"):
        save_sensor_calibration(worse, path, cam, proj)
    save_sensor_calibration(worse, path, cam, proj, force=True)
    with pytest.raises(ConfigError, match="resolution mismatch"):
        load_sensor_model(path, cam.model_copy(update={"width_px": 320}))


def test_bad_steps_are_refused(rig):
    ps = gcls_patterns(128, 96, 8, 8, "both")
    rng = np.random.default_rng(2)
    cal = SensorCalibrator(rig.sensor.camera, rig.sensor.projector, rig.sensor.standoff_mm, n_points=256)
    d0 = decode(rig.capture(0.0, ps.frames, rng), ps, 12)
    with pytest.raises(CalibrationError, match="height 0"):
        cal.add_step(1.0, d0)
    cal.add_step(0.0, d0)
    with pytest.raises(CalibrationError, match="not above"):
        cal.add_step(0.0, d0)
    with pytest.raises(CalibrationError, match="at least 3"):
        cal.finish()
    cols = gcls_patterns(128, 96, 8, 8, "columns")
    with pytest.raises(CalibrationError, match="both stripe directions"):
        cal.add_step(1.0, decode(rig.capture(1.0, cols.frames, rng), cols, 12))
