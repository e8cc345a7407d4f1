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
    """Measure a glass pane: view vectors, marker search, multi-camera feedback, error map and report."""
    from rich.console import Console

    from cell.devices import build_glass_rig
    from cell.errors import ConfigError
    from cell.glass.config import load_glass_recipe, load_glass_rig
    from cell.glass.job import run_glass_inspection
    from cell.mesh import load_mesh
    from cell.runs import RunFolder

    rec = load_glass_recipe(recipe)
    if method is not None:
        if method not in ("golden_section", "multi_projection"):
            raise ConfigError(f"--method {method!r}: use golden_section or multi_projection", field="method")
        rec.search.method = method  # type: ignore[assignment]
    rig_path = cell or rec.rig
    cfg = load_glass_rig(rig_path)
    if rec.search.method == "multi_projection" and cfg.screen.second_T_W_S is None:
        raise ConfigError(
            "the multi-projection method needs the screen's second known position: add "
            "screen.second_T_W_S to the rig config",
            path=str(rig_path),
            field="screen",
        )
    T_W_P = rec.part.T_W_P.matrix()
    nominal_W = load_mesh(rec.part.cad, what="nominal pane").apply_transform(T_W_P)
    actual_path = sim_actual or rec.part.actual or rec.part.cad
    actual_W = load_mesh(actual_path, what="simulated actual pane").apply_transform(T_W_P)
    part = rec.name or rec.part.cad.stem
    run = RunFolder.create(out.parent, part, name=out.name)
    inputs = (
        (recipe, "recipe.yaml"),
        (rig_path, "rig.yaml"),
        (rec.part.cad, "nominal" + rec.part.cad.suffix),
        (actual_path, "actual" + Path(actual_path).suffix),
    )
    for src, name in inputs:
        run.copy_input(Path(src), name)
    run.log("run_created", part=part, recipe=str(recipe), rig=str(rig_path), actual=str(actual_path))
    rig, place_board, move_screen = build_glass_rig(cfg, actual_W, _operator_places_board)
    summary = run_glass_inspection(
        run, rec, cfg, rig, place_board, nominal_W, frames, board_frames, move_screen
    )
    dev = summary["deviation"]
    console = Console()
    console.print(
        f"[bold]verdict: {str(summary['verdict']).upper()}[/]  ({summary['n_points']} of "
        f"{summary['markers']} points accepted; deviation {dev.get('min_mm', float('nan')):.3f} .. "
        f"{dev.get('max_mm', float('nan')):.3f} mm)"
    )
    console.print(f"report: {run.results_dir / 'report.html'}")


def _operator_places_board(height_mm: float | None) -> None:
    """On a real rig the technician (or a lift) places the dot-grid board at each calibration height."""
    what = f"the calibration board at {height_mm:g} mm" if height_mm is not None else "the board away"
    typer.confirm(f"Place {what}, then confirm", abort=True)


def register(app: typer.Typer) -> None:
    app.command("glass")(glass_cmd)
