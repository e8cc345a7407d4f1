"""``cell plan RECIPE --out DIR``: the initial CAD-guided view plan f0 as DIR/plan.json and DIR/plan.png."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
import trimesh
import typer

from cell.analysis.regions import check_region_faces
from cell.config import DEFAULT_CELL, CellConfig, Recipe, load_cell_config, load_recipe
from cell.errors import PlanningError
from cell.geometry import transform_points
from cell.mesh import check_in_volume, load_mesh
from cell.planning.planner import Plan, plan_initial
from cell.planning.settings import PlanSettings


def working_volume_W(cfg: CellConfig) -> tuple[np.ndarray, np.ndarray]:
    """World box (mm) the part must fit in: the robot envelope mapped into {W}, from the table top up."""
    T_W_B = cfg.robot.T_W_B.matrix()
    lo, hi = np.asarray(cfg.robot.envelope_min_mm), np.asarray(cfg.robot.envelope_max_mm)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    cw = transform_points(T_W_B, corners)
    return np.r_[cw.min(axis=0)[:2], -1.0], cw.max(axis=0)


def load_part_W(recipe: Recipe, recipe_path: Path, cfg: CellConfig) -> trimesh.Trimesh:
    """The validated nominal CAD placed in the world; ConfigError when it does not fit the cell or the
    recipe's face regions name faces it does not have."""
    mesh = load_mesh(recipe.part.cad)
    check_region_faces(recipe.regions, len(mesh.faces), recipe_path, prefix="regions.")
    T_W_P = recipe.part.T_W_P.matrix()
    lo, hi = working_volume_W(cfg)
    check_in_volume(mesh, recipe.part.cad, lo, hi, T_W_P)
    return mesh.copy().apply_transform(T_W_P)


def make_plan(recipe_path: Path, cell_path: Path, settings: PlanSettings | None = None) -> Plan:
    cfg = load_cell_config(cell_path)
    recipe = load_recipe(recipe_path)
    return plan_initial(load_part_W(recipe, recipe_path, cfg), cfg, settings or recipe.plan)


def write_plan(plan: Plan, out: Path) -> None:
    """Write plan.json atomically (temp file + rename) and plan.png."""
    from cell.planning.picture import draw_plan

    out.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out, suffix=".json.tmp")
    os.fchmod(fd, 0o644)
    with os.fdopen(fd, "w") as f:
        json.dump(plan.to_json(), f, indent=1)
    draw_plan(plan, out / "plan.png")
    os.replace(tmp, out / "plan.json")


def plan_cmd(
    recipe: Path = typer.Argument(..., help="recipe YAML"),
    out: Path = typer.Option(..., "--out", help="output folder for plan.json and plan.png"),
    cell: Path = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML"),
) -> None:
    """Plan the initial viewpoints of a recipe's part (CAD-guided, bounding-box method)."""
    plan = make_plan(recipe, cell)
    if not plan.viewpoints:
        raise PlanningError(
            f"{recipe}: no reachable viewpoint covers any of the part; check part.T_W_P and the "
            "cell's robot envelope"
        )
    write_plan(plan, out)
    typer.echo(
        f"{len(plan.viewpoints)} viewpoints, predicted coverage {100 * plan.coverage:.2f}% of "
        f"{plan.surface.inspectable_area_mm2:.0f} mm^2 inspectable, planned in {plan.planning_time_s:.2f} s "
        f"-> {out / 'plan.json'}"
    )


def register(app: typer.Typer) -> None:
    app.command("plan")(plan_cmd)
