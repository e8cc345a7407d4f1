"""Command-line values of plain types converted without pydantic: a command's start costs a tenth of a second.

typer 0.29 converts every option value through a pydantic ``TypeAdapter``: the first value it converts
imports pydantic (about 0.15 s of CPU, half of the 0.3 s start-up budget), even a missing one (``None``) and
even the ``--help`` flag of the ``cell`` group when a command follows. :func:`install` puts a converter in
front of typer's for the types the commands use -- ``str``, ``int``, ``float``, ``bool`` and ``Path`` without
a custom parser -- that

- returns a missing value (``None``) as typer does, without building anything;
- converts the plain spellings itself, with the result pydantic gives them (``"12"`` -> 12, ``"0.5"`` ->
  0.5, a path through typer's own path checks);
- hands everything else (another spelling, a value outside ``min``/``max``, a bad value) to typer's own
  pydantic converter, so accepted spellings and error messages stay typer's.

tests/test_cli_coercion.py checks it value by value against typer's converter. If a typer release renames
what this relies on, :func:`install` does nothing and the commands are only slower (tests/test_cli.py then
sees pydantic load for ``--help``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

_INT = re.compile(r"[+-]?(0|[1-9][0-9]{0,17})")
_FLOAT = re.compile(r"[+-]?(0|[1-9][0-9]{0,17})(\.[0-9]{1,17})?([eE][+-]?[0-9]{1,3})?")
_SLOW = object()  # "not a plain spelling: ask typer"


def _plain_number(annotation: type, info: Any, value: Any) -> Any:
    """``value`` (a string from the command line, or the default) as ``annotation``, or _SLOW."""
    if isinstance(value, str):
        if annotation is int and _INT.fullmatch(value):
            number: Any = int(value)
        elif annotation is float and _FLOAT.fullmatch(value) and math.isfinite(float(value)):
            number = float(value)
        else:
            return _SLOW
    elif type(value) is annotation:  # a default written in the code
        number = value
    else:
        return _SLOW
    if (
        info.clamp
        or (info.min is not None and number < info.min)
        or (info.max is not None and number > info.max)
    ):
        return _SLOW  # typer clamps or words the error
    return number


def _is_plain(descriptor: Any) -> bool:
    """Whether the parameter is one this module converts (else typer alone does)."""
    info = descriptor.parameter_info
    return (
        descriptor.annotation in (str, int, float, bool, Path)
        and info.parser is None
        and descriptor.file_annotation is None
        and getattr(info, "path_type", None) in (None, Path)
    )


def install() -> bool:
    """Put the plain converter in front of typer's; True when it is in place (idempotent)."""
    try:
        import typer.core as core
        from typer._coercion import RuntimeParam
        from typer._param_types import coerce_cli_path
    except ImportError:
        return False
    if not callable(getattr(core, "build_runtime_param", None)) or not isinstance(RuntimeParam, type):
        return False
    typer_build: Callable[[Any], Any] = core.build_runtime_param
    if getattr(typer_build, "_cell_plain", False):
        return True

    @dataclass(frozen=True)
    class PlainRuntimeParam(RuntimeParam):
        """A value of a plain type: converted here when plainly spelt, else by typer's own converter."""

        descriptor: Any = None

        def _coerce_value(self, value: Any, param: Any, ctx: Any) -> Any:
            annotation, info = self.annotation, self.parameter_info
            if annotation is str and isinstance(value, str):
                return value
            if annotation is bool and isinstance(value, bool):
                return value
            if annotation in (int, float):
                number = _plain_number(annotation, info, value)
                if number is not _SLOW:
                    return number
            if annotation is Path and isinstance(value, (str, Path)) and str(value):
                return coerce_cli_path(Path(value), info, path_type=Path, param=param, ctx=ctx)
            return typer_build(self.descriptor)._coerce_value(value, param=param, ctx=ctx)

    def build_runtime_param(descriptor: Any) -> Any:
        if _is_plain(descriptor):
            return PlainRuntimeParam(
                parameter_info=descriptor.parameter_info,
                annotation=descriptor.annotation,
                descriptor=descriptor,
            )
        return typer_build(descriptor)

    build_runtime_param._cell_plain = True  # type: ignore[attr-defined]
    build_runtime_param.typer_build = typer_build  # type: ignore[attr-defined]  # typer's own, for the tests
    core.build_runtime_param = build_runtime_param
    return True
