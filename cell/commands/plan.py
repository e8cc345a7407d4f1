"""``cell plan RECIPE --out DIR``: the initial CAD-guided view plan f0 as DIR/plan.json and DIR/plan.png, and
the cycle-time limit of its tour (motion + capture) with its breakdown."""

from __future__ import annotations

from pathlib import Path

import typer


def plan_cmd(
    recipe: Path = typer.Argument(..., help="recipe YAML"),
    out: Path = typer.Option(..., "--out", help="output folder for plan.json and plan.png"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
) -> None:
    """Plan the initial viewpoints of a recipe's part (CAD-guided, bounding-box method) and print the
    cycle-time limit of the tour (motion + capture)."""
    from cell.config import DEFAULT_CELL, load_cell_config
    from cell.errors import PlanningError
    from cell.planning.cycle_time import cycle_time, inspection_frames
    from cell.planning.planner import plan_recipe, write_plan
    from cell.runs import require_empty_output

    cell = cell or DEFAULT_CELL
    require_empty_output(out)
    plan = plan_recipe(recipe, cell)
    if not plan.viewpoints:
        raise PlanningError(
            f"{recipe}: no reachable viewpoint covers any of the part; check part.T_W_P and the "
            "cell's robot envelope"
        )
    cfg = load_cell_config(cell)
    limit = cycle_time(cfg, [v.T_B_T for v in plan.viewpoints], inspection_frames(cfg))
    write_plan(plan, out, {"cycle_time": limit.to_json()})
    typer.echo(
        f"{len(plan.viewpoints)} viewpoints, predicted coverage {100 * plan.coverage:.2f}% of "
        f"{plan.surface.inspectable_area_mm2:.0f} mm^2 inspectable, planned in {plan.planning_time_s:.2f} s "
        f"-> {out / 'plan.json'}"
    )
    typer.echo(limit.summary())


def register(app: typer.Typer) -> None:
    app.command("plan")(plan_cmd)
