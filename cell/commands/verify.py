"""``cell verify acceptance`` (the VDI/VDE 2634 Part 2 or Part 3 acceptance test of the cell), ``cell verify
check`` (the short interim check, stored in the runs root's history with a drift warning) and ``cell verify
history``: argument parsing and printing around cell.verification.job and cell.verification.history."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from cell.defaults import DEFAULT_CELL, RUNS_ROOT

if TYPE_CHECKING:
    from cell.verification.procedure import AcceptanceResult

verify_app = typer.Typer(
    help="Acceptance test and re-verification after VDI/VDE 2634 (sphere, ball bar, plane).",
    no_args_is_help=True,
)


@verify_app.command("acceptance")
def acceptance_cmd(
    out: Path = typer.Option(..., "--out", help="run folder to write (an unfinished one is resumed)"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    certificate: Path = typer.Option(
        None, "--certificate", help="artefact certificate YAML (default: the cell's verification.certificate)"
    ),
    part: int = typer.Option(
        2, "--part", help="2: one view, ball bar and plane in 13 positions; 3: the long bar across views"
    ),
) -> None:
    """Part 2: the ball bar (7 positions) and the plane (6 positions) in the single-view measuring volume.
    Part 3: the long ball bar in 3 directions, each across 4 views of the robot-moved sensor. Runs under the
    controller (pause with Ctrl-C, run again to resume); writes report.html and verification.json to OUT and
    prints PF, PS, SD and F against their MPEs. Exit code 0 whatever the verdict (the report holds it); an
    acceptance test is a record in its folder, not part of the shift history `cell verify check` keeps."""
    typer.echo(f"VDI/VDE 2634 part {part} acceptance test of cell {cell or DEFAULT_CELL} -> {out}")
    from cell.verification.job import acceptance_test

    result = acceptance_test(cell, certificate, out, part, on_progress=_progress())
    _print_figures(result)
    typer.echo(f"verdict: {result.verdict} -> {Path(out) / 'report.html'}")


def _progress() -> Callable[[Any], None]:
    """A progress callback that prints each newly measured view once."""
    shown: set[int] = set()

    def progress(controller: Any) -> None:
        done, total = controller.views_done, controller.views_total
        if total and done not in shown:
            shown.add(done)
            typer.echo(f"view {done}/{total}")

    return progress


def _print_figures(result: AcceptanceResult) -> None:
    for k, v in result.figures_mm.items():
        sign = "+" if k in ("PS", "SD") else ""
        shown_value = "not measured" if v is None else f"{v * 1000:{sign}.1f} um"
        status = {True: "pass", False: "FAIL", None: "-"}[result.passed[k]]
        mpe = f"{'+-' if sign else ''}{result.mpe_mm[k] * 1000:.1f}"
        typer.echo(f"{k:>2}: {shown_value:>14}  (MPE {mpe} um)  {status}")


@verify_app.command("check")
def check_cmd(
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    certificate: Path = typer.Option(None, "--certificate", help="artefact certificate YAML"),
    runs: Path = typer.Option(RUNS_ROOT, "--runs", help="runs root (its results.sqlite by default)"),
) -> None:
    """The interim check for the start of a shift: one ball-bar and one plane position. Its figures join the
    verification history in RUNS; warns when a figure drifts toward its MPE, exits 1 when one exceeds it."""
    typer.echo(f"interim check of cell {cell or DEFAULT_CELL} -> the history in {runs}")
    from cell.verification.job import interim_check

    result, folder, warnings = interim_check(cell, certificate, runs, on_progress=_progress())
    _print_figures(result)
    for warning in warnings:
        typer.echo(f"WARNING: {warning}")
    typer.echo(f"check: {result.verdict} -> {folder / 'report.html'}")
    if result.verdict == "fail":
        raise typer.Exit(1)


@verify_app.command("history")
def history_cmd(
    cell: str = typer.Option(None, "--cell-name", help="only this cell (its config's name)"),
    runs: Path = typer.Option(RUNS_ROOT, "--runs", help="runs root (its results.sqlite by default)"),
    config: Path = typer.Option(None, "--cell", help="cell config whose results_db to read"),
) -> None:
    """Every stored interim check, oldest first: PF, PS, SD, F (um) and the verdict."""
    # what it reads, before the database layer's import (SQLAlchemy: 0.2 s of CPU) and the query
    from cell.commands.history import results_db_label

    where = results_db_label(runs, config)
    typer.echo(f"interim checks{f' of cell {cell}' if cell else ''} in {where}, oldest first")
    from cell.verification.history import FIGURES, VerificationHistory

    cfg = None
    if config:
        from cell.config import load_cell_config

        cfg = load_cell_config(config)
    entries = VerificationHistory(runs, cfg).entries(cell)
    typer.echo(f"{'time':<26}{'kind':<12}{'cell':<24}" + "".join(f"{k:>9}" for k in FIGURES) + "  verdict")
    for e in entries:
        values = "".join(
            f"{'-':>9}" if (x := e.figures_mm[k]) is None else f"{x * 1000:>9.1f}" for k in FIGURES
        )
        typer.echo(f"{e.time:<26}{e.kind:<12}{e.cell:<24}{values}  {e.verdict}")


def register(app: typer.Typer) -> None:
    app.add_typer(verify_app, name="verify")
