"""``cell calibrate``: runs on a small simulated cell, writes calibration.json, refuses bad input and never
replaces a better calibration without --force."""

from __future__ import annotations

import json

import pytest
import yaml

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


def test_sensor_and_gamma_commands(tmp_path, small_cell):
    out = tmp_path / "cal"
    main(["calibrate", "sensor", "--cell", str(small_cell), "--out", str(out), "--steps", "6",
          "--step-mm", "4", "--points", "256"])
    report = json.loads((out / "calibration.json").read_text())
    assert report["kind"] == "sensor_per_pixel"
    assert report["summary"]["d_mm"]["mean"] == pytest.approx(300.0, rel=0.03)  # small_sensor's baseline
    assert (out / "sensor.yaml").exists() and (out / "journal.jsonl").exists()
    # a second run that is worse (fewer points, same images otherwise) must not replace the first
    code = _run(["calibrate", "sensor", "--cell", str(small_cell), "--out", str(out), "--steps", "3",
                 "--step-mm", "1", "--points", "64", "--seed", "5"])
    assert code == 1
    g = tmp_path / "gamma"
    main(["calibrate", "gamma", "--cell", str(small_cell), "--out", str(g)])
    assert json.loads((g / "calibration.json").read_text())["summary"]["fitted_gamma"] == pytest.approx(1.0,
                                                                                                          abs=0.05)


def test_bad_inputs(tmp_path, small_cell):
    assert _run(["calibrate", "sensor", "--cell", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert _run(["calibrate", "validate", str(tmp_path / "nothing.yaml"), "--cell", str(small_cell),
                 "--out", str(tmp_path / "v")]) == 2
