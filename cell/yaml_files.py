"""Reading one YAML file a person gives the cell and validating it against its schema, with errors that
name the file and the field (:class:`cell.errors.ConfigError`). Apart from cell.config (which re-exports both)
so that a small file such as the station's users list is read without the cell config's schemas and numpy.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from cell.errors import ConfigError
from cell.schema_errors import meant_key, unknown_key_message, wrong_kind_message

M = TypeVar("M", bound=BaseModel)


def _field_path(loc: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; ConfigError naming the file when it is missing, unreadable or not a mapping."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError("file not found; check the path", path=str(p))
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"malformed YAML{where}: {getattr(exc, 'problem', exc)}", path=str(p)) from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read: {exc}", path=str(p)) from exc
    if not isinstance(data, dict):
        raise ConfigError("expected a mapping of keys to values at the top level", path=str(p))
    return data


def _problems(model: type[BaseModel], errors: list[Any]) -> list[tuple[str, str]]:
    """(field path, message) of each of pydantic's errors, in its order. A misspelled required key is both
    an unknown key and a missing one: one problem, the typo (its "did you mean"), not two."""
    typos = {
        (*e["loc"][:-1], meant): e["loc"]
        for e in errors
        if e["type"] == "extra_forbidden" and (meant := meant_key(model, e["loc"])) is not None
    }
    out = []
    for err in errors:
        if err["type"] == "missing" and tuple(err["loc"]) in typos:
            continue
        if err["type"] == "extra_forbidden":
            msg = unknown_key_message(model, err["loc"])
        elif err["type"] == "missing":
            msg = "required field is missing"
        else:
            msg = err["msg"]
        out.append((_field_path(err["loc"]), msg))
    return out


def validate(model: type[M], data: dict[str, Any], path: str | Path) -> M:
    """Validate ``data`` against ``model``; a ConfigError naming file and field, or with several problems
    one naming the file and listing each problem on a line of its own (file and field). A file of another
    known kind (a recipe where a cell config belongs) is said to be one, alone; an unknown key gets the
    closest known key ("did you mean")."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        wrong_kind = wrong_kind_message(model, data) if isinstance(data, dict) else None
        if wrong_kind:
            raise ConfigError(wrong_kind, path=str(path)) from exc
        problems = _problems(model, exc.errors())
        if len(problems) == 1:
            raise ConfigError(problems[0][1], path=str(path), field=problems[0][0]) from exc
        listed = "".join(f"\n  {path}: field '{field}': {msg}" for field, msg in problems)
        raise ConfigError(f"{len(problems)} problems:{listed}", path=str(path)) from exc
