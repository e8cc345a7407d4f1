"""What the ``cell calibrate`` command modules (cell/commands/calibrate.py and calibrate_cell.py) share:
their options, the first line each prints before its heavy imports, and running and printing a routine."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from cell.defaults import DEFAULT_CELL

CellOpt = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML")
OutOpt = typer.Option(..., "--out", help="run folder to write (an unfinished one is resumed)")
ForceOpt = typer.Option(False, "--force", help="replace a better existing calibration")
FromOpt = typer.Option(
    None,
    "--from",
    help="capture folder of images taken elsewhere (docs/capture-folders.md); no device is used",
)


def start(routine: str, cell: Path, out: Path, source: Path | None = None) -> None:
    """The command's first line, before anything heavy is imported: which routine, on what, into where."""
    what = f"capture folder {source}" if source is not None else f"cell {cell}"
    typer.echo(f"calibrate {routine}: {what} -> {out}")


def cell_config(cell: Path) -> Any:
    """The validated cell config (cell.config is imported here, after the command's first line)."""
    from cell.config import load_cell_config

    return load_cell_config(cell)


def print_result(result: dict[str, Any]) -> None:
    """A routine's figures, and the cell config lines that use its calibration file (if a field takes it)."""
    from cell.calibration.store import config_lines

    typer.echo(json.dumps(result.get("summary", result), indent=2, default=str))
    lines = config_lines(result.get("kind", ""), result.get("file", ""))
    if lines:
        typer.echo(
            "\nTo use it, put this into the cell config (paths may be made relative to the cell file):\n"
            + lines
        )


def run(job: Any, out: Path, cell: Path, seed: int) -> None:
    """Run the routine ``job`` into ``out`` (cell.calibration.routines.run_routine) and print its result."""
    from cell.calibration.routines import run_routine

    print_result(run_routine(job, out, cell, seed=seed))


def offline(routine: str, source: Path, out: Path, cell: Path, **options: Any) -> None:
    """Run ``routine`` on the capture folder ``source`` (cell.calibration.offline) and print its result."""
    from cell.calibration.offline import calibrate_from_folder

    print_result(calibrate_from_folder(routine, source, out, cell, **options))
