"""``cell calibrate``: runs on a small simulated cell, writes calibration.json, refuses bad input and never
replaces a better calibration without --force."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from cell.calibration.store import save_calibration
from cell.cli import main
from cell.config import DEFAULT_CELL
from fakes.sim.testing import small_sensor


@pytest.fixture()
def small_cell(tmp_path):
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    sensor = small_sensor().model_dump(mode="json")
    sensor["T_T_C"] = data["sensor"]["T_T_C"]
    data["sensor"] = sensor
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _run(args):
    with pytest.raises(SystemExit) as exc:
        main(args)
    return exc.value.code


def _calibrate_sensor(cell, out) -> None:
    """`cell calibrate sensor` on the small rig: 6 steps of 4 mm, 256 code points."""
    main(
        [
            "calibrate",
            "sensor",
            "--cell",
            str(cell),
            "--out",
            str(out),
            "--steps",
            "6",
            "--step-mm",
            "4",
            "--points",
            "256",
        ]
    )


def test_sensor_and_gamma_commands(tmp_path, small_cell):
    # The robot holds its pose while the stage steps the board (it lands once, +-0.03 mm): d's mean was
    # 297.6-298.9 mm over six noise draws (--seed 1-6, bench/trace_sensor_routine.py --small) against the
    # world's 300.05 mm baseline: the routine's own bias (-0.66 % in the binned honest world,
    # docs/calibration.md) and 1.3 mm of spread. When the simulator landed the held robot afresh at every step
    # it swung over 290.7-331.2 mm, mostly outside the 1.5 % (295.5-304.5 mm) asked here.
    out = tmp_path / "cal"
    _calibrate_sensor(small_cell, out)
    report = json.loads((out / "calibration.json").read_text())
    assert report["kind"] == "sensor_per_pixel"
    assert report["summary"]["d_mm"]["mean"] == pytest.approx(300.0, rel=0.015)  # small_sensor's baseline
    assert (out / "sensor.yaml").exists() and (out / "journal.jsonl").exists()
    # a short run (3 x 1 mm) predicts heights at the far end of the depth of field far worse than the 6 x 4 mm
    # one on disk: refused without --force, accepted with it
    ypath = out / "sensor.yaml"
    good = yaml.safe_load(ypath.read_text())["quality"]["height_sigma_mm"]
    args = [
        "calibrate",
        "sensor",
        "--cell",
        str(small_cell),
        "--out",
        str(out),
        "--steps",
        "3",
        "--points",
        "256",
    ]
    assert _run(args) == 1
    assert yaml.safe_load(ypath.read_text())["quality"]["height_sigma_mm"] == good
    main([*args, "--force"])
    assert yaml.safe_load(ypath.read_text())["quality"]["height_sigma_mm"] > 10 * good
    g = tmp_path / "gamma"
    main(["calibrate", "gamma", "--cell", str(small_cell), "--out", str(g)])
    assert json.loads((g / "calibration.json").read_text())["summary"]["fitted_gamma"] == pytest.approx(
        1.0, abs=0.05
    )


def test_bad_inputs(tmp_path, small_cell):
    assert (
        _run(["calibrate", "sensor", "--cell", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")])
        == 2
    )
    assert (
        _run(
            [
                "calibrate",
                "validate",
                str(tmp_path / "nothing.yaml"),
                "--cell",
                str(small_cell),
                "--out",
                str(tmp_path / "v"),
            ]
        )
        == 2
    )


def test_intrinsics_command_and_force_rule(tmp_path, capsys):
    # the binned camera in sim.yaml's world: the force rule does not need the full camera's pixels
    binned = ["--cell", str(DEFAULT_CELL.parent / "sim_binned_honest.yaml")]
    out = tmp_path / "intr"
    main(["calibrate", "intrinsics", *binned, "--out", str(out), "--views", "6"])
    report = json.loads((out / "calibration.json").read_text())
    assert report["summary"]["rms_px"] < 0.1
    assert f"intrinsics: {(out / 'intrinsics.yaml').resolve()}" in capsys.readouterr().out  # for the config
    ypath = out / "intrinsics.yaml"
    meta = yaml.safe_load(ypath.read_text())
    meta["quality"]["rms_px"] = 0.0  # pretend the file on disk is perfect: a new run is worse
    ypath.write_text(yaml.safe_dump(meta))
    assert _run(["calibrate", "intrinsics", *binned, "--out", str(out), "--views", "6"]) == 1
    assert yaml.safe_load(ypath.read_text())["quality"]["rms_px"] == 0.0  # kept
    main(["calibrate", "intrinsics", *binned, "--out", str(out), "--views", "6", "--force"])
    assert yaml.safe_load(ypath.read_text())["quality"]["rms_px"] > 0.0
    few = ["calibrate", "intrinsics", *binned, "--out", str(tmp_path / "few"), "--views", "2"]
    assert _run(few) == 1  # too few


def test_active_calibration_from_cell_config(tmp_path, small_cell):
    from cell.calibration import (
        active_hand_eye,
        active_sensor_config,
        active_triangulator,
        calibration_source,
    )
    from cell.config import load_cell_config
    from cell.sensing.triangulate import PinholeTriangulator, ReferencePlaneTriangulator

    cfg = load_cell_config(small_cell)
    assert isinstance(active_triangulator(cfg), PinholeTriangulator)
    assert calibration_source(cfg) == "config geometry (no calibration)"
    np.testing.assert_array_equal(active_hand_eye(cfg), cfg.sensor.T_T_C.matrix())
    out = tmp_path / "cal"
    _calibrate_sensor(small_cell, out)
    T = np.eye(4)
    T[:3, 3] = (1.0, -61.0, 80.5)
    save_calibration(tmp_path / "handeye", "hand_eye", {"T_T_C": T}, {})
    data = yaml.safe_load(small_cell.read_text())
    data["calibration"] = {"sensor": "cal/sensor.yaml", "hand_eye": "handeye.yaml"}
    small_cell.write_text(yaml.safe_dump(data))
    cfg = load_cell_config(small_cell)
    model = active_triangulator(cfg)
    assert isinstance(model, ReferencePlaneTriangulator) and model.d.shape == (120, 160)
    np.testing.assert_array_equal(active_hand_eye(cfg), T)
    assert calibration_source(cfg).startswith("sensor: sensor.yaml (")
    np.testing.assert_array_equal(active_sensor_config(cfg).T_T_C.matrix(), T)


def test_validate_command_plane_sphere_and_slots(tmp_path, small_cell):
    out = tmp_path / "cal"
    args = ["--cell", str(small_cell), "--steps", "6", "--step-mm", "5", "--points", "256"]
    main(["calibrate", "sensor", "--out", str(out), *args])
    v = tmp_path / "val"
    main(["calibrate", "validate", str(out / "sensor.yaml"), "--cell", str(small_cell), "--out", str(v)])
    summary = json.loads((v / "validation.json").read_text())["summary"]
    # the small rig (1 px/mm), its lenses, projector pose and hand-eye off as sim.yaml's world puts them; its
    # decoding limits it to ~0.2 mm on a sphere (tests/test_calib_sensor.py::test_sphere_test). The centre and
    # plane height are in the world frame through the uncalibrated hand-eye, so they are not asserted here.
    sphere = summary["sphere"]
    assert sphere["true_radius_mm"] == 12.5 and sphere["points"] > 300
    assert abs(sphere["radius_error_mm"]) < 0.3 and sphere["std_mm"] < 0.15
    # 0.03 (was 0.02 in the ideal world): the camera lens here is the config's, 0.5 % off the world's
    assert summary["plane"]["std_mm"] < 0.05 and abs(summary["flat"]["mean_mm"]) < 0.03
    # the flat test is only valid where the camera saw the reference plane from: the same pose here
    assert summary["flat"]["reference_pose_change_mm"] < 0.1
    # the slot gauge against its certificate (Fig 5.4): at 1 px/mm a point's noise is ~0.027 mm and ~600
    # points per slot floor average it to ~2 um, but the per-pixel model of this short run (256 points, d
    # scattered by 7 mm a point) errs in height alike over a slot's few mm: over 16 noise draws of the two
    # routines (--seed k, k and k, k+1 for k = 1-4, before and after their noise was restarted per view) the
    # deepest slot's depth erred by -8.4 to +9.6 um (4.4 um rms; this draw +9.6)
    slots = summary["slots"]["slots"]
    assert [s["nominal_um"] for s in slots] == [32.0, 24.0, 14.0, 6.0]
    assert slots[0]["resolved"] and abs(slots[0]["measured_um"] - 32.0) < 12.0
