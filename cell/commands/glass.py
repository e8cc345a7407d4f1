"""``cell glass``: back-imaging inspection of a glass pane on the (simulated) glass rig (docs/glass.md).

The rig config is the recipe's ``rig`` file unless ``--cell`` names another glass rig config (the cell config
has no glass section yet). Only the simulated rig exists: it renders ``--sim-actual`` (default: the recipe's
``part.actual``, else the nominal pane).
"""

from __future__ import annotations

from pathlib import Path

import typer


def glass_cmd(
    recipe: Path = typer.Argument(..., help="glass recipe YAML (recipes/glass/pane.yaml)"),
    out: Path = typer.Option(..., "--out", help="run folder to create (must not exist or be empty)"),
    cell: Path = typer.Option(None, "--cell", help="glass rig config YAML (default: the recipe's rig)"),
    sim_actual: Path = typer.Option(None, "--sim-actual", help="simulation: mesh rendered as the made pane"),
    frames: int = typer.Option(4, "--frames", min=1, help="grabs averaged per camera for the measurement"),
    board_frames: int = typer.Option(8, "--board-frames", min=1, help="grabs averaged per board height"),
    method: str = typer.Option(
        None,
        "--method",
        help="override the recipe's search.method: golden_section "
        "or multi_projection (2.4; the rig must define screen.second_T_W_S)",
    ),
) -> None:
    """Measure a glass pane: view vectors, marker search, multi-camera feedback, error map and report. Exits
    0 on pass, 4 on fail, 5 when incomplete (docs/exit-codes.md)."""
    typer.echo(f"glass inspection of {recipe} on {cell or 'its rig'} -> {out}")
    from rich.console import Console

    from cell.exit_codes import ExitCode, for_verdict
    from cell.glass.job import inspect_glass

    run, summary = inspect_glass(
        recipe, out, cell, sim_actual, frames, board_frames, method, _operator_places_board
    )
    dev = summary["deviation"]
    console = Console()
    console.print(
        f"verdict: {str(summary['verdict']).upper()}  ({summary['n_points']} of "
        f"{summary['markers']} points accepted; deviation {dev.get('min_mm', float('nan')):.3f} .. "
        f"{dev.get('max_mm', float('nan')):.3f} mm)",
        style="bold",
        markup=False,
    )
    console.print(f"report: {run.results_dir / 'report.html'}", markup=False)
    code = for_verdict(summary["verdict"])
    if code is not ExitCode.PASS:
        raise typer.Exit(int(code))


def _operator_places_board(height_mm: float | None) -> None:
    """On a real rig the technician (or a lift) places the dot-grid board at each calibration height."""
    what = f"the calibration board at {height_mm:g} mm" if height_mm is not None else "the board away"
    typer.confirm(f"Place {what}, then confirm", abort=True)


def register(app: typer.Typer) -> None:
    app.command("glass")(glass_cmd)
