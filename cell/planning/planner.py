"""The initial plan f0 (eq 3.13, M -> V0): patches, bounding-box viewpoints, a model-based fill of predicted
holes, pruning of redundant views, reachability and the tour order. Every decision goes to ``Plan.log``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.config import CellConfig
from cell.geometry import Pose
from cell.planning.clustering import cluster_points
from cell.planning.coverage import coverage_fraction, predicted_masks
from cell.planning.kinematics import UR5E
from cell.planning.patches import cluster_patches
from cell.planning.reach import ReachChecker
from cell.planning.sensor_model import SensorModel
from cell.planning.settings import PlanSettings
from cell.planning.surface import PartSurface, sample_surface
from cell.planning.tour import order_tour, pose_costs
from cell.planning.viewpoints import PatchPlanner, Viewpoint

FILL_ROUNDS = 2
SMALL_PATCH_SHARE = 0.05  # patches under this share of the field area are left to the hole fill pass


@dataclass
class Plan:
    """Ordered viewpoints with their predicted coverage, and the context the feedback loop continues from."""

    viewpoints: list[Viewpoint]
    predicted: NDArray[np.bool_]  # (V, N) samples each viewpoint is predicted to measure
    coverage: float  # predicted share of the inspectable area
    planning_time_s: float
    log: list[dict[str, Any]]
    surface: PartSurface
    sensor: SensorModel
    patch_planner: PatchPlanner
    face_patch: NDArray[np.int64] = field(repr=False, default_factory=lambda: np.zeros(0, dtype=np.int64))

    def to_json(self) -> dict[str, Any]:
        return {
            "coverage": self.coverage,
            "planning_time_s": self.planning_time_s,
            "inspectable_area_mm2": self.surface.inspectable_area_mm2,
            "viewpoints": [
                {
                    "index": k,
                    "patch": v.patch,
                    "source": v.source,
                    "T_W_C": v.T_W_C.tolist(),
                    "T_B_T": v.T_B_T.tolist(),
                    "patch_fraction": v.patch_fraction,
                    "predicted_coverage": float(
                        self.surface.area[self.predicted[k]].sum()
                        / max(self.surface.inspectable_area_mm2, 1e-12)
                    ),
                }
                for k, v in enumerate(self.viewpoints)
            ],
            "log": self.log,
        }


def plan_initial(
    mesh_W: trimesh.Trimesh,
    cfg: CellConfig,
    settings: PlanSettings | None = None,
    exclude_faces: Sequence[int] = (),
) -> Plan:
    """Plan V0 for a validated part mesh in world coordinates (mm). ``exclude_faces`` (indices into the mesh's
    faces: a recipe's ``exclude_from_coverage``) are left out of the inspectable surface: no viewpoint is
    planned for them and coverage does not count them."""
    t0 = time.perf_counter()
    st = settings or PlanSettings()
    sensor = SensorModel.from_config(cfg, st)
    surface = sample_surface(mesh_W, st.samples, st.seed, sensor.standoff_mm, np.deg2rad(st.theta_camera_deg))
    excluded = surface.inspectable & np.isin(surface.face, np.asarray(exclude_faces, dtype=np.int64))
    surface = replace(surface, inspectable=surface.inspectable & ~excluded)
    log: list[dict[str, Any]] = [
        {
            "event": "surface",
            "reason": "sampled the nominal surface",
            "samples": len(surface.points),
            "inspectable_area_mm2": round(surface.inspectable_area_mm2, 1),
            "area_mm2": round(float(mesh_W.area), 1),
        }
    ]
    if len(exclude_faces):
        log.append(
            {
                "event": "excluded",
                "reason": "the recipe's exclude_from_coverage",
                "faces": len(set(exclude_faces)),
                "area_mm2": round(float(surface.area[excluded].sum()), 1),
            }
        )
    reach = ReachChecker(cfg, np.vstack([mesh_W.vertices, surface.points]), st.clearance_mm)
    pp = PatchPlanner(sensor, surface, reach, log)
    face_patch = cluster_patches(mesh_W, np.deg2rad(st.patch_cone_deg))
    sample_patch = np.where(surface.inspectable, face_patch[surface.face], -1)
    labels, counts = np.unique(sample_patch[sample_patch >= 0], return_counts=True)
    log.append(
        {
            "event": "patches",
            "reason": f"eqs 3.1-3.2 with a {st.patch_cone_deg:.0f} deg cone",
            "patches": int(len(labels)),
            "planned": int(
                (
                    np.bincount(
                        np.maximum(sample_patch, 0), weights=np.where(sample_patch >= 0, surface.area, 0.0)
                    )[labels]
                    >= SMALL_PATCH_SHARE * np.prod(sensor.fov_mm)
                ).sum()
            ),
        }
    )
    views: list[Viewpoint] = []
    small = SMALL_PATCH_SHARE * np.prod(sensor.fov_mm)
    areas = np.bincount(np.maximum(sample_patch, 0), weights=np.where(sample_patch >= 0, surface.area, 0.0))
    masks = np.zeros((0, len(surface.points)), dtype=bool)
    for lab in labels[np.argsort(-counts, kind="stable")]:
        if areas[lab] < small:
            continue  # small patches (fillets, edges) are covered by neighbours or by the fill pass
        todo = np.flatnonzero((sample_patch == lab) & ~masks.any(axis=0))
        if surface.area[todo].sum() < small:
            log.append(
                {
                    "event": "patch_covered",
                    "patch": f"P{lab}",
                    "reason": "viewpoints of larger patches already measure all but a small share of it",
                }
            )
            continue
        added = pp.plan(todo, f"P{lab}", "f0")
        views += added
        masks = np.vstack([masks, predicted_masks(sensor, surface, [v.T_W_C for v in added])])
    for rnd in range(FILL_ROUNDS):
        holes = np.flatnonzero(surface.inspectable & ~masks.any(axis=0))
        added = fill_holes(pp, holes, f"H{rnd}.", "f0-fill", log)
        if not added:
            break
        views += added
        masks = np.vstack([masks, predicted_masks(sensor, surface, [v.T_W_C for v in added])])
    views, masks = prune(views, masks, surface.area, st.min_patch_area_mm2, log)
    views, masks = order_views(views, masks, cfg)
    cov = coverage_fraction(surface, np.any(masks, axis=0))
    dt = time.perf_counter() - t0
    log.append(
        {
            "event": "plan",
            "reason": "initial plan f0 done",
            "viewpoints": len(views),
            "predicted_coverage": round(cov, 4),
            "planning_time_s": round(dt, 3),
        }
    )
    return Plan(views, masks, cov, dt, log, surface, sensor, pp, face_patch)


def fill_holes(
    pp: PatchPlanner, holes: NDArray[np.int64], prefix: str, source: str, log: list[dict[str, Any]]
) -> list[Viewpoint]:
    """Cluster hole samples (link = 3 x the mean sample spacing) and plan viewpoints for clusters that are
    larger than ``min_patch_area_mm2``."""
    s = pp.surface
    if len(holes) == 0:
        return []
    spacing = np.sqrt(s.area.mean())
    lab = cluster_points(s.points[holes], 3.0 * spacing)
    out: list[Viewpoint] = []
    for k in range(int(lab.max()) + 1):
        idx = holes[lab == k]
        a = float(s.area[idx].sum())
        if a < pp.sensor.settings.min_patch_area_mm2:
            log.append(
                {
                    "event": "hole_ignored",
                    "patch": f"{prefix}{k}",
                    "area_mm2": round(a, 1),
                    "reason": "hole smaller than min_patch_area_mm2",
                }
            )
            continue
        log.append(
            {
                "event": "hole",
                "patch": f"{prefix}{k}",
                "area_mm2": round(a, 1),
                "source": source,
                "reason": "uncovered inspectable surface: plan a viewpoint for it",
            }
        )
        out += pp.plan(idx, f"{prefix}{k}", source)
    return out


def prune(
    views: list[Viewpoint],
    masks: NDArray[np.bool_],
    area: NDArray[np.float64],
    min_area: float,
    log: list[dict[str, Any]],
) -> tuple[list[Viewpoint], NDArray[np.bool_]]:
    """Drop views whose unique contribution is under ``min_area`` mm^2, least useful first."""
    keep = np.ones(len(views), dtype=bool)
    for k in np.argsort(masks @ area, kind="stable"):
        others = masks[keep & (np.arange(len(views)) != k)].any(axis=0)
        unique = float(area[masks[k] & ~others].sum())
        if unique < min_area:
            keep[k] = False
            log.append(
                {
                    "event": "pruned",
                    "patch": views[k].patch,
                    "unique_area_mm2": round(unique, 1),
                    "reason": "other viewpoints already measure what this one would",
                }
            )
    return [v for v, k in zip(views, keep) if k], masks[keep]


def order_views(
    views: list[Viewpoint], masks: NDArray[np.bool_], cfg: CellConfig
) -> tuple[list[Viewpoint], NDArray[np.bool_]]:
    """Tour from the view nearest the robot's home pose: nearest neighbour + 2-opt."""
    if len(views) < 2:
        return views, masks
    home_T_W_C: Pose = (
        cfg.robot.T_W_B.matrix() @ UR5E.fk(np.deg2rad(cfg.robot.home_joints_deg)) @ cfg.sensor.T_T_C.matrix()
    )
    cost = pose_costs([home_T_W_C] + [v.T_W_C for v in views])
    tour = [i - 1 for i in order_tour(cost, 0)[1:]]
    return [views[i] for i in tour], masks[tour]


def plan_recipe(recipe_path: Path, cell_path: Path, settings: PlanSettings | None = None) -> Plan:
    """The initial plan of a recipe file's part on a cell config file (the recipe's plan settings unless
    ``settings`` is given)."""
    from cell.config import load_cell_config, load_recipe
    from cell.mesh import load_part_W

    cfg = load_cell_config(cell_path)
    recipe = load_recipe(recipe_path)
    part_W = load_part_W(recipe, recipe_path, cfg)
    return plan_initial(part_W, cfg, settings or recipe.plan, recipe.exclude_from_coverage)


def write_plan(plan: Plan, out: Path, extra: dict[str, Any] | None = None) -> None:
    """Write ``out/plan.json`` atomically (temp file + rename), with the ``extra`` keys added (e.g. the
    cycle-time limit), and ``out/plan.png``."""
    from cell.planning.picture import draw_plan

    out.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out, suffix=".json.tmp")
    os.fchmod(fd, 0o644)
    with os.fdopen(fd, "w") as f:
        json.dump({**plan.to_json(), **(extra or {})}, f, indent=1)
    draw_plan(plan, out / "plan.png")
    os.replace(tmp, out / "plan.json")
