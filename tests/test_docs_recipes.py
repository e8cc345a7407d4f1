"""Every YAML example in docs/recipes.md is a recipe the cell accepts: a whole recipe is validated and planned
(`cell plan`), a fragment (regions, alignment, exclude_from_coverage) is validated in the demo recipe as
`cell inspect` checks a recipe before its run starts (schema, faces against the CAD, datums on the part)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from cell.config import DEFAULT_CELL, load_cell_config, load_recipe

REPO = Path(__file__).resolve().parent.parent
DOC = REPO / "docs" / "recipes.md"
EXAMPLES = re.findall(r"^```yaml\n(.*?)^```", DOC.read_text(encoding="utf-8"), flags=re.M | re.S)


def _is_recipe(example: str) -> bool:
    return {"part", "tolerance"} <= set(yaml.safe_load(example))


def test_the_page_has_its_examples() -> None:
    """The extraction finds them: whole recipes and fragments both."""
    assert len(EXAMPLES) >= 5
    assert sum(map(_is_recipe, EXAMPLES)) >= 2 and sum(not _is_recipe(e) for e in EXAMPLES) >= 3


def _in_recipes_folder(tmp_path: Path, data: dict) -> Path:
    """The example as a recipe file whose relative paths resolve as they would in recipes/."""
    (tmp_path / "parts").symlink_to(REPO / "recipes" / "parts")
    path = tmp_path / "example.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("example", [e for e in EXAMPLES if _is_recipe(e)], ids=lambda e: e.split("\n")[0])
def test_a_whole_recipe_example_plans(example: str, tmp_path: Path, capsys) -> None:
    from cell.cli import main

    path = _in_recipes_folder(tmp_path, yaml.safe_load(example))
    load_recipe(path)
    main(["plan", str(path), "--out", str(tmp_path / "plan")])
    assert "viewpoints, predicted coverage" in capsys.readouterr().out
    assert (tmp_path / "plan" / "plan.json").is_file()


@pytest.mark.parametrize(
    "example", [e for e in EXAMPLES if not _is_recipe(e)], ids=lambda e: next(iter(yaml.safe_load(e)))
)
def test_a_fragment_example_is_valid_in_the_demo_recipe(example: str, tmp_path: Path) -> None:
    from cell.analysis.alignment import check_datums
    from cell.geometry import invert
    from cell.mesh import load_part_W

    data = {**yaml.safe_load((REPO / "recipes" / "pillar.yaml").read_text()), **yaml.safe_load(example)}
    path = _in_recipes_folder(tmp_path, data)
    recipe = load_recipe(path)
    part_W = load_part_W(recipe, path, load_cell_config(DEFAULT_CELL))  # faces against the CAD
    check_datums(
        recipe.alignment.datums, part_W.apply_transform(invert(recipe.part.T_W_P.matrix())), str(path)
    )
    assert _holds(recipe.model_dump(mode="json"), yaml.safe_load(example))  # read as written, nothing dropped


def _holds(loaded: object, given: object) -> bool:
    """Every value of ``given`` (the example) is in ``loaded`` (the validated recipe, defaults filled in)."""
    if isinstance(given, dict):
        return isinstance(loaded, dict) and all(
            k in loaded and _holds(loaded[k], v) for k, v in given.items()
        )
    if isinstance(given, list):
        return isinstance(loaded, list) and len(loaded) == len(given) and all(map(_holds, loaded, given))
    return loaded == given
