"""Planning time of the initial plan f0: the demo pillar (~20k triangles) and the pillar subdivided to >= 200k
triangles; for the pillar also the view count of a greedy set cover over the same candidate poses (the
baseline of docs/planning-baseline.md). Run: ``.venv/bin/python bench/bench_plan.py``; prints one line per
part and one for the baseline."""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.config import DEFAULT_CELL, load_cell_config
from cell.mesh import load_mesh
from cell.planning.coverage import coverage_fraction, predicted_masks
from cell.planning.planner import Plan, plan_initial

ROOT = Path(__file__).resolve().parent.parent


def greedy_cover(masks: NDArray[np.bool_], area: NDArray[np.float64], target_area: float) -> list[int]:
    """Indices of chosen candidates (rows of ``masks``, (V, N)) covering >= ``target_area`` of ``area``: the
    classic ln(n)-approximate greedy set cover, each step taking the candidate adding the most uncovered
    area."""
    covered = np.zeros(masks.shape[1], dtype=bool)
    chosen: list[int] = []
    while area[covered].sum() < target_area - 1e-9:
        gain = (masks & ~covered) @ area
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(k)
        covered |= masks[k]
    return chosen


def greedy_baseline(plan: Plan) -> str:
    """Greedy set cover over every reachable pose the planner evaluated, up to the planner's predicted
    covered area: whether the bounding-box planner needs more views than the baseline."""
    s = plan.surface
    masks = predicted_masks(plan.sensor, s, plan.patch_planner.candidates)
    target = float(s.area[s.inspectable & plan.predicted.any(axis=0)].sum())
    chosen = greedy_cover(masks, s.area, target)
    cov = coverage_fraction(s, masks[chosen].any(axis=0))
    return (
        f"greedy set cover over the same {len(masks)} candidates: {len(chosen)} viewpoints, "
        f"predicted coverage {100 * cov:.2f}%"
    )


def main() -> None:
    cfg = load_cell_config(DEFAULT_CELL)
    pillar = load_mesh(ROOT / "recipes/parts/pillar_nominal.stl")
    big = pillar.subdivide().subdivide()  # 4 x 4 = 16 x the triangles
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
    for name, mesh in (("pillar", pillar), ("pillar x16", big)):
        t = time.perf_counter()
        plan = plan_initial(mesh, cfg)
        dt = time.perf_counter() - t
        print(
            f"{name}: {len(mesh.faces)} triangles, {len(plan.viewpoints)} viewpoints, predicted coverage "
            f"{100 * plan.coverage:.2f}%, planning {dt:.2f} s"
        )
        if name == "pillar":
            print(f"{name}: {greedy_baseline(plan)}")


if __name__ == "__main__":
    main()
