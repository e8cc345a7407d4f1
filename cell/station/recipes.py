"""The recipes a station offers: every ``*.yaml`` in its recipes folder that loads as a recipe. The page names
a recipe by its file's stem; anything else is an unknown recipe. A technician edits a recipe's YAML; the new
text is validated as a recipe (schema, CAD files) before it replaces the file."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from cell.config import load_recipe
from cell.errors import ConfigError
from cell.runs import write_atomic


@dataclass(frozen=True)
class RecipeEntry:
    """One recipe file: its key (the file's stem), the part it inspects, and why it cannot run (or None)."""

    key: str
    path: Path
    part: str
    problem: str | None = None


def list_recipes(folder: Path) -> list[RecipeEntry]:
    """Every recipe file in ``folder``, sorted by key; an invalid one carries its problem."""
    out = []
    for path in sorted(folder.glob("*.yaml")):
        if path.name.startswith("."):
            continue
        try:
            recipe = load_recipe(path)
        except ConfigError as exc:
            out.append(RecipeEntry(path.stem, path, "?", str(exc)))
            continue
        out.append(RecipeEntry(path.stem, path, recipe.name or recipe.part.cad.stem))
    return out


def find_recipe(folder: Path, key: str) -> RecipeEntry:
    """The recipe ``key`` names; ConfigError when there is none (or it is invalid)."""
    for entry in list_recipes(folder):
        if entry.key == key:
            if entry.problem:
                raise ConfigError(f"recipe '{key}' cannot run: {entry.problem}", field="recipe")
            return entry
    raise ConfigError(
        f"unknown recipe '{key}': there is no {key}.yaml in the recipes folder {folder} (removed or renamed "
        "since the page was loaded?); pick one from the list",
        field="recipe",
    )


def save_recipe(folder: Path, key: str, text: str) -> None:
    """Replace recipe ``key`` by ``text`` once ``text`` loads as a recipe (checked in a hidden file beside
    it, so relative CAD paths resolve as they will); ConfigError with the problem otherwise, the file as it
    was."""
    entry = next((e for e in list_recipes(folder) if e.key == key), None)
    if entry is None:
        raise ConfigError(f"unknown recipe '{key}'", field="recipe")
    trial = folder / f".{key}.check-{os.getpid()}.yaml"
    try:
        trial.write_text(text, encoding="utf-8")
        try:
            load_recipe(trial)
        except ConfigError as exc:
            raise ConfigError(str(exc).replace(str(trial), entry.path.name)) from None
    finally:
        trial.unlink(missing_ok=True)
    write_atomic(entry.path, text.encode("utf-8"))
