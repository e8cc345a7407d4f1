"""``cell plan RECIPE --out DIR``: the initial CAD-guided view plan f0 as DIR/plan.json and DIR/plan.png, the
cycle-time limit of its tour (motion + capture) with its breakdown, and what the recipe author should know:
a predicted coverage below the recipe's min_coverage, and the surfaces no reachable viewpoint sees."""

from __future__ import annotations

from pathlib import Path

import typer


def plan_cmd(
    recipe: Path = typer.Argument(..., help="recipe YAML"),
    out: Path = typer.Option(..., "--out", help="output folder for plan.json and plan.png"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
) -> None:
    """Plan the initial viewpoints of a recipe's part (CAD-guided, bounding-box method) and print the
    cycle-time limit of the tour (motion + capture). Warns when the predicted coverage is below the recipe's
    min_coverage and names the surfaces that no reachable viewpoint sees (with their CAD faces, for the
    recipe's exclude_from_coverage)."""
    from cell.defaults import DEFAULT_CELL

    typer.echo(f"planning the views of {recipe} on cell {cell or DEFAULT_CELL} -> {out}")
    from cell.config import load_cell_config, load_recipe
    from cell.errors import PlanningError
    from cell.planning.cycle_time import cycle_time, inspection_frames
    from cell.planning.planner import plan_recipe, write_plan
    from cell.planning.unseen import plan_feedback
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
    feedback = plan_feedback(plan, load_recipe(recipe))
    write_plan(plan, out, {"cycle_time": limit.to_json(), **feedback.to_json()})
    typer.echo(
        f"{len(plan.viewpoints)} viewpoints, predicted coverage {100 * plan.coverage:.2f}% of "
        f"{plan.surface.inspectable_area_mm2:.0f} mm^2 inspectable, planned in {plan.planning_time_s:.2f} s "
        f"-> {out / 'plan.json'}"
    )
    typer.echo(limit.summary())
    for warning in feedback.warnings:
        typer.echo(f"warning: {warning}", err=True)
    if feedback.unseen and not feedback.warnings:
        typer.echo("seen by no planned viewpoint (coverage is still above min_coverage):")
        for surface in feedback.unseen:
            typer.echo(f"  {surface.describe()}")


def register(app: typer.Typer) -> None:
    app.command("plan")(plan_cmd)
