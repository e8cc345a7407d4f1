"""Planning time of the initial plan f0: the demo pillar (~20k triangles) and the pillar subdivided to >= 200k
triangles. Run: ``.venv/bin/python bench/bench_plan.py``; prints one line per part."""

from __future__ import annotations

import platform
import time
from pathlib import Path

from cell.config import DEFAULT_CELL, load_cell_config
from cell.mesh import load_mesh
from cell.planning.planner import plan_initial

ROOT = Path(__file__).resolve().parent.parent


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


if __name__ == "__main__":
    main()
