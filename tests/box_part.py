"""A small box part, its recipe and a small simulated cell: fast end-to-end runs of the controller and CLI."""

from __future__ import annotations

from pathlib import Path

import trimesh
import yaml

from cell.config import DEFAULT_CELL, CellConfig, load_cell_config
from fakes.sim.testing import small_sensor


def small_cell() -> CellConfig:
    """The default simulated cell with the 160x120 test sensor (same robot, hand-eye and scene) in the IDEAL
    world (the simulator renders the config's geometry): the controller and resume tests check states,
    faults and that a resumed run repeats an uninterrupted one, and judge the nominal box as passing."""
    cfg = load_cell_config(DEFAULT_CELL)
    sensor = small_sensor(bit_depth=8).model_dump()
    sensor["T_T_C"] = cfg.sensor.T_T_C.model_dump()
    return CellConfig.model_validate({**cfg.model_dump(), "sensor": sensor, "world": "ideal"})


# where the robot reaches every face of the box: the planner splits no unreachable face down to its smallest
# patches, and a whole inspection takes about a fifth of the time it takes at the world origin (measured 8 s
# against 37 s on the shared 2-core machine)
IN_REACH_MM = (0.0, -60.0, 0.0)


def write_box_recipe(folder: Path, at_mm: tuple[float, float, float] | None = IN_REACH_MM) -> Path:
    """A 120 x 90 x 40 mm box on the table and its recipe; returns the recipe path.

    ``at_mm`` places the part (part.T_W_P): by default at :data:`IN_REACH_MM`, where every face is in the
    robot's reach; None leaves it at the world origin, where the robot cannot reach its +y face.
    """
    box = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))
    box.export(folder / "box.stl")
    recipe = {
        "name": "box",
        "part": {"cad": "box.stl"},
        "tolerance": {"lower": -0.3, "upper": 0.3},
        "min_coverage": 0.6,  # at the origin the box's +y face is out of the robot's reach
        "plan": {"resolution_mm": 1.5, "point_density_per_mm2": 0.2, "view_budget": 8, "max_iterations": 1},
    }
    if at_mm is not None:
        recipe["part"]["T_W_P"] = {"xyz_mm": [float(v) for v in at_mm]}
    (folder / "box.yaml").write_text(yaml.safe_dump(recipe))
    return folder / "box.yaml"


# the dent write_dented_box_recipe presses into the box's top face (part frame, mm): a raised-cosine cap
DENT = {"centre_mm": (25.0, 15.0, 40.0), "radius_mm": 12.0, "depth_mm": 0.8}


def write_dented_box_recipe(folder: Path) -> Path:
    """The box recipe (:func:`write_box_recipe`, in reach) whose simulated actual part has :data:`DENT` in its
    top face, and a recipe region ``lid`` (a box around the top face); returns the recipe path. The nominal
    is the plain box, so the inspection fails with the dent as its largest defect."""
    import numpy as np

    recipe = write_box_recipe(folder)
    box = trimesh.load(folder / "box.stl")
    vertices, faces = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=1.5)
    top = np.isclose(vertices[:, 2], 40.0)
    r = np.linalg.norm(vertices[:, :2] - np.asarray(DENT["centre_mm"][:2]), axis=1)
    push = DENT["depth_mm"] * 0.5 * (1.0 + np.cos(np.pi * np.clip(r / DENT["radius_mm"], 0.0, 1.0)))
    vertices[top, 2] -= push[top]
    trimesh.Trimesh(vertices, faces, process=True).export(folder / "box_dented.stl")
    doc = yaml.safe_load(recipe.read_text())
    doc["part"]["actual"] = "box_dented.stl"
    doc["regions"] = [{"name": "lid", "box_mm": [[-60.0, -45.0, 35.0], [60.0, 45.0, 41.0]]}]
    recipe.write_text(yaml.safe_dump(doc))
    return recipe
