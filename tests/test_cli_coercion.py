"""cell.cli_coercion converts option values as typer's own pydantic converter does, value by value: the same
result of the same type, or the same error message."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import typer
import typer.core
from typer._click import Context
from typer._click.exceptions import BadParameter

from cell import cli_coercion

assert cli_coercion.install()

app = typer.Typer()


@app.command()
def every_kind(
    text: str = typer.Option("a"),
    count: int = typer.Option(3),
    at_least_one: int = typer.Option(1, min=1),
    ratio: float = typer.Option(0.5),
    step: float = typer.Option(1.0, min=0.01),
    percent: int = typer.Option(50, min=0, max=100, clamp=True),
    folder: Path = typer.Option(Path("x")),
    flag: bool = typer.Option(False),
) -> None:
    """A command with one option of each kind the cell's commands use."""


COMMAND = typer.main.get_command(app)
PARAMS = {p.name: p for p in COMMAND.params}
INTS = [
    "0",
    "7",
    "-3",
    "+4",
    "007",
    "-0",
    "1_000",
    " 5",
    "5 ",
    "1.0",
    "1e3",
    "abc",
    "",
    "99999999999999999999",
]
FLOATS = [
    "0.5",
    "-2",
    "2",
    "1e-3",
    "1E3",
    "+.5",
    ".5",
    "5.",
    "-0.0",
    "inf",
    "nan",
    "1_0.5",
    "abc",
    "",
    "1e400",
]
VALUES: dict[str, list[Any]] = {
    "text": ["x", "", "ü ber", "--", "12"],
    "count": INTS + [12, 12.0, True],
    "at_least_one": ["0", "1", "5", "-1", 0, 1],
    "ratio": FLOATS + [0.25, 3],
    "step": ["0.001", "0.01", "0.5", "0", "-1"],
    "percent": ["-5", "0", "50", "100", "150"],
    "folder": ["a/b", "", ".", "tests", "tests/test_cli_coercion.py", "no/such/file", Path("y")],
    "flag": [True, False, "true", "1", "no", "", "maybe"],
}


def convert(build: Any, name: str, value: Any) -> tuple[str, Any]:
    param = PARAMS[name]
    ctx = Context(COMMAND)
    try:
        return "ok", build(param.type_descriptor).coerce(value, param=param, ctx=ctx)
    except BadParameter as exc:
        return "error", exc.format_message()


@pytest.mark.parametrize("name", list(VALUES))
def test_plain_values_convert_as_typer_converts_them(name: str) -> None:
    ours, theirs = typer.core.build_runtime_param, typer.core.build_runtime_param.typer_build
    assert ours is not theirs  # installed
    for value in [*VALUES[name], None]:
        got, want = convert(ours, name, value), convert(theirs, name, value)
        assert repr(got) == repr(want) and type(got[1]) is type(want[1]), (name, value, got, want)


def test_what_it_does_not_know_is_typers_alone() -> None:
    """A list option or a custom parser is not converted here at all."""
    from typer._coercion import resolve_type_descriptor
    from typer.models import OptionInfo

    for annotation, info in ((list[int], OptionInfo()), (int, OptionInfo(parser=int))):
        assert not cli_coercion._is_plain(resolve_type_descriptor(annotation, info))
    assert cli_coercion._is_plain(resolve_type_descriptor(Path, OptionInfo()))
