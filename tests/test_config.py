"""Cell config and recipe loading: valid files load, bad ones give errors that name file and field."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.config import DEFAULT_CELL, load_cell_config, load_recipe
from cell.errors import ConfigError

REPO = Path(__file__).resolve().parent.parent


def _write_cell(tmp_path: Path, mutate) -> Path:
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    mutate(data)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_default_cell_matches_the_prototype_geometry() -> None:
    cfg = load_cell_config(DEFAULT_CELL)
    cam = cfg.sensor.camera
    # field of view at the stand-off: width = W * S / fx, about 200 x 150 mm (dissertation 2.1.4)
    assert cam.width_px * cfg.sensor.standoff_mm / cam.fx_px == pytest.approx(200, abs=2)
    assert cam.height_px * cfg.sensor.standoff_mm / cam.fy_px == pytest.approx(150, abs=2)
    T_C_P = cfg.sensor.projector.T_C_P.matrix()
    assert np.linalg.norm(T_C_P[:3, 3]) == pytest.approx(429.3)  # baseline d
    # the projector's optical axis passes through the field centre on the reference plane
    axis = T_C_P[:3, 2]
    t = -T_C_P[0, 3] / axis[0]
    centre = T_C_P[:3, 3] + t * axis
    assert centre[2] == pytest.approx(cfg.sensor.standoff_mm, abs=1.0)


@pytest.mark.parametrize(
    ("mutate", "field", "words"),
    [
        (lambda d: d["sensor"]["camera"].update(fx_pix=2000), "sensor.camera.fx_pix", "unknown key"),
        (lambda d: d["sensor"].pop("standoff_mm"), "sensor.standoff_mm", "missing"),
        # a misspelled required key is both unknown and missing: the typo is named, not the missing key
        (
            lambda d: d["sensor"].update(standof_mm=d["sensor"].pop("standoff_mm")),
            "sensor.standof_mm",
            "typo",
        ),
        (lambda d: d["sensor"].update(standoff_mm=0.3937), "sensor.standoff_mm", "greater than 50"),
        (lambda d: d["robot"].update(envelope_min_mm=[1000, 0, 0]), "robot", "envelope_min_mm"),
        (lambda d: d["sensor"]["camera"].update(bit_depth=9), "sensor.camera.bit_depth", ""),
    ],
)
def test_bad_cell_config_names_file_and_field(tmp_path: Path, mutate, field: str, words: str) -> None:
    path = _write_cell(tmp_path, mutate)
    with pytest.raises(ConfigError) as info:
        load_cell_config(path)
    message = str(info.value)
    assert str(path) in message
    assert field in message
    assert words in message


def test_malformed_yaml_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("name: x\nrobot: [unclosed\n")
    with pytest.raises(ConfigError, match=r"broken.yaml: malformed YAML at line \d+"):
        load_cell_config(path)


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nowhere.yaml: file not found"):
        load_cell_config(tmp_path / "nowhere.yaml")


def test_recipe_paths_are_relative_to_the_recipe(tmp_path: Path) -> None:
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "p.stl").write_text("solid x\nendsolid x\n")
    recipe = tmp_path / "r.yaml"
    recipe.write_text("part: {cad: parts/p.stl}\ntolerance: {lower: -0.2, upper: 0.2}\n")
    loaded = load_recipe(recipe)
    assert loaded.part.cad == (tmp_path / "parts" / "p.stl").resolve()


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("part: {cad: missing.stl}\ntolerance: {lower: -0.2, upper: 0.2}\n", "part.cad"),
        ("part: {cad: p.stl}\ntolerance: {lower: 0.2, upper: 0.3}\n", "tolerance.lower"),
        ("part: {cad: p.stl}\ntolerance: {lower: -200, upper: 0.3}\n", "not a plausible tolerance"),
        ("part: {cad: p.stl}\n", "tolerance"),
    ],
)
def test_bad_recipe(tmp_path: Path, text: str, words: str) -> None:
    (tmp_path / "p.stl").write_text("solid x\nendsolid x\n")
    recipe = tmp_path / "r.yaml"
    recipe.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_recipe(recipe)
    assert "r.yaml" in str(info.value) and words in str(info.value)


def test_cli_exits_2_on_bad_config_and_writes_nothing(tmp_path: Path) -> None:
    path = _write_cell(tmp_path, lambda d: d["robot"].update(max_tcp_speed_mm_s=-1))
    before = set(tmp_path.iterdir())
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "devices", "--cell", str(path)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "robot.max_tcp_speed_mm_s" in proc.stderr and str(path) in proc.stderr.replace("\n", "")
    assert set(tmp_path.iterdir()) == before
