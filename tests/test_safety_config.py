"""What a person who wrote the wrong thing is told: the key they probably meant, that the file is of another
kind altogether, that a tolerance is in metres. Every message names the file and the field."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from cell.config import DEFAULT_CELL, load_cell_config, load_recipe
from cell.errors import ConfigError
from cell.file_kinds import FILE_KINDS

REPO = Path(__file__).resolve().parent.parent
PART = "part: {cad: p.stl}\n"
BAND = "tolerance: {lower: -0.3, upper: 0.3}\n"


def _error(load, path: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load(path)
    return str(info.value)


def _recipe(tmp_path: Path, text: str) -> Path:
    (tmp_path / "p.stl").write_text("solid x\nendsolid x\n")
    path = tmp_path / "r.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("mutate", "field", "meant"),
    [
        (lambda d: d["sensor"]["camera"].update(fx_pix=2000), "sensor.camera.fx_pix", "fx_px"),
        (
            lambda d: d["sensor"].update(standof_mm=d["sensor"].pop("standoff_mm")),
            "sensor.standof_mm",
            "standoff_mm",
        ),
        (lambda d: d["robot"]["T_W_B"].update(xyz=[0, 0, 0]), "robot.T_W_B.xyz", "xyz_mm"),
        (lambda d: d.update(calibraton={}), "calibraton", "calibration"),
        (
            lambda d: d.update(world={"hand_eyes": {}}),
            "world.hand_eyes",
            "hand_eye",
        ),  # the simulator's schema
    ],
)
def test_a_misspelled_cell_config_key_gets_the_key_meant(
    tmp_path: Path, mutate, field: str, meant: str
) -> None:
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    mutate(data)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    message = _error(load_cell_config, path)
    assert str(path) in message and f"field '{field}'" in message
    assert f"did you mean '{meant}'?" in message


@pytest.mark.parametrize(
    ("text", "field", "meant"),
    [
        (PART + "tolerence: {lower: -0.3, upper: 0.3}\n", "tolerence", "tolerance"),
        (PART + BAND + "plan: {view_budgt: 3}\n", "plan.view_budgt", "view_budget"),
        (
            PART + BAND + "regions: [{name: a, faces: [1], tolerance: [-1, 1]}]\n",
            "regions.0.tolerance",
            "tolerance_mm",
        ),
        (
            PART + BAND + "alignment: {datums: [{name: a, point: [0, 0, 0]}]}\n",
            "alignment.datums.0.point",
            "point_mm",
        ),
        (PART + BAND + "exclude_from_coverge: [1]\n", "exclude_from_coverge", "exclude_from_coverage"),
    ],
)
def test_a_misspelled_recipe_key_gets_the_key_meant(
    tmp_path: Path, text: str, field: str, meant: str
) -> None:
    message = _error(load_recipe, _recipe(tmp_path, text))
    assert "r.yaml" in message and f"field '{field}'" in message and f"did you mean '{meant}'?" in message


def test_an_unknown_key_like_no_other_lists_the_keys_there(tmp_path: Path) -> None:
    message = _error(load_recipe, _recipe(tmp_path, PART + "tolerance: {lower: -0.3, upper: 0.3, zzz: 1}\n"))
    assert "field 'tolerance.zzz'" in message and "the keys here are: lower, upper" in message


def test_region_file_and_certificate_keys_get_the_key_meant(tmp_path: Path) -> None:
    from cell.analysis.regions import load_regions
    from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate

    regions = tmp_path / "regions.yaml"
    regions.write_text("regions: [{name: seal, box: [[0, 0, 0], [1, 1, 1]]}]\n")
    message = _error(load_regions, regions)
    assert (
        str(regions) in message and "field 'regions.0.box'" in message and "did you mean 'box_mm'?" in message
    )
    data = yaml.safe_load(DEFAULT_CERTIFICATE.read_text())
    data["plane"]["flatnes_mm"] = data["plane"].pop("flatness_mm", 0.001)
    cert = tmp_path / "cert.yaml"
    cert.write_text(yaml.safe_dump(data))
    message = _error(load_certificate, cert)
    assert "field 'plane.flatnes_mm'" in message and "did you mean 'flatness_mm'?" in message


def _loader(name: str):
    module, attr = name.split(":")
    return getattr(importlib.import_module(module), attr)


@pytest.mark.parametrize(
    ("given", "loader", "says"),
    [
        (
            "recipes/glass/rig_sim.yaml",
            "cell.config:load_cell_config",
            "a glass rig config file, not a cell config",
        ),
        ("recipes/pillar.yaml", "cell.config:load_cell_config", "a recipe file, not a cell config file"),
        ("recipes/cells/sim.yaml", "cell.config:load_recipe", "a cell config file, not a recipe file"),
        ("recipes/glass/pane.yaml", "cell.config:load_recipe", "a glass recipe file, not a recipe file"),
        (
            "recipes/artefacts/certificate.yaml",
            "cell.config:load_recipe",
            "an artefact certificate file, not a",
        ),
        (
            "recipes/pillar.yaml",
            "cell.glass.config:load_glass_rig",
            "a recipe file, not a glass rig config file",
        ),
        (
            "recipes/cells/sim.yaml",
            "cell.verification.certificate:load_certificate",
            "a cell config file, not an",
        ),
        (
            "recipes/parts/gauge.certificate.yaml",
            "cell.analysis.regions:load_regions",
            "a gauge certificate file",
        ),
    ],
)
def test_a_file_of_another_kind_is_named_as_such(given: str, loader: str, says: str) -> None:
    message = _error(_loader(loader), REPO / given)
    assert f"this is {says}" in message and given in message
    assert "unknown key" not in message  # one mistake, not a list of typos


def test_a_recipe_with_a_typo_is_still_a_recipe(tmp_path: Path) -> None:
    """A recipe whose required key is misspelled and that has regions is not taken for a region file."""
    text = PART + "tolerence: {lower: -0.3, upper: 0.3}\nregions: [{name: a, faces: [0]}]\n"
    message = _error(load_recipe, _recipe(tmp_path, text))
    assert "did you mean 'tolerance'?" in message and "this is" not in message


def test_the_cli_says_which_kind_the_file_is(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "plan", "recipes/cells/sim.yaml", "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "this is a cell config file, not a recipe file" in lines[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kind", FILE_KINDS, ids=lambda k: k.name)
def test_the_file_kinds_table_matches_each_schema(kind) -> None:
    """The table is data (cell.config cannot import the glass package); it must say what each schema says."""
    if kind.schema is None:  # a calibration file: written by cell.calibration.store, no schema
        from cell.calibration import store

        source = Path(store.__file__).read_text()
        assert all(f'"{key}"' in source for key in kind.required)
        return
    model = _loader(kind.schema)
    assert kind.required == {k for k, f in model.model_fields.items() if f.is_required()}
    assert kind.allowed == set(model.model_fields)


@pytest.mark.parametrize(
    ("text", "field"),
    [
        (PART + "tolerance: {lower: -0.0003, upper: 0.0003}\n", "tolerance.lower"),
        (PART + "tolerance: {lower: -0.3, upper: 0.0005}\n", "tolerance.upper"),
        (
            PART + BAND + "regions: [{name: seal, faces: [0], tolerance_mm: [-0.00005, 0.00005]}]\n",
            "regions.0",
        ),
    ],
)
def test_a_tolerance_in_metres_is_refused_in_a_recipe(tmp_path: Path, text: str, field: str) -> None:
    message = _error(load_recipe, _recipe(tmp_path, text))
    assert f"field '{field}'" in message and "in metres?" in message


def test_a_tolerance_in_metres_is_refused_in_a_region_file_but_a_one_sided_band_is_not(
    tmp_path: Path,
) -> None:
    from cell.analysis.regions import load_regions

    path = tmp_path / "regions.yaml"
    path.write_text("regions: [{name: seal, faces: [0], tolerance_mm: [-0.0002, 0.0002]}]\n")
    message = _error(load_regions, path)
    assert str(path) in message and "field 'regions.0'" in message and "in metres?" in message
    path.write_text("regions: [{name: seal, faces: [0], tolerance_mm: [0, 0.2]}]\n")  # no removal allowed
    assert load_regions(path)[0].tolerance_mm == (0.0, 0.2)


def test_every_problem_of_a_file_is_listed_on_a_line_with_file_and_field(tmp_path: Path, capsys) -> None:
    """Three mistakes in one recipe: the command says all three (one error, exit code 2), each on a line of
    its own naming the file and the field; a misspelled required key is one problem (the typo), not also a
    missing key."""
    from cell.cli import main

    text = (
        PART
        + "tolerence: {lower: -0.3, upper: 0.3}\n"  # the typo of a required key
        + "plan: {view_budgt: 3}\n"
        + "min_coverage: 2\n"
    )
    recipe = _recipe(tmp_path, text)
    with pytest.raises(SystemExit) as ended:
        main(["plan", str(recipe), "--out", str(tmp_path / "o")])
    assert ended.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {recipe}: 3 problems:")
    lines = err.strip().splitlines()[1:]
    assert len(lines) == 3 and all(line.startswith(f"  {recipe}: field '") for line in lines)
    said = "\n".join(lines)
    assert "field 'tolerence': unknown key (typo?); did you mean 'tolerance'?" in said
    assert "field 'plan.view_budgt': unknown key (typo?); did you mean 'view_budget'?" in said
    assert "field 'min_coverage': Input should be less than or equal to 1" in said
    assert "missing" not in err and "more problem" not in err
    assert not (tmp_path / "o").exists()
