"""Benchmark the scene renderer: one frame at a new pose, and a 40-pattern stack at one pose, per cell config.

    .venv/bin/python bench/bench_render.py [--json] [--repeat N]

The scene is the table and a 200x120x40 mm box; the camera looks down from the stand-off (an oblique
projector lights it, so shadows and occlusion are exercised). Patterns are 40 binary stripe images.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cell.config import load_cell_config
from cell.geometry import look_at
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene

CELLS = Path(__file__).resolve().parent.parent / "recipes" / "cells"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _patterns(width: int, height: int, n: int = 40) -> list[np.ndarray]:
    u = np.arange(width)
    return [
        np.repeat(np.where((u >> (k % 10)) & 1, 255, 0).astype(np.uint8)[None, :], height, 0)
        for k in range(n)
    ]


def bench(cell_file: Path, repeat: int) -> dict[str, float | str]:
    cfg = load_cell_config(cell_file)
    box = trimesh.creation.box(bounds=[[-100.0, -60.0, 0.0], [100.0, 60.0, 40.0]])
    renderer = SceneRenderer(cfg.sensor, cfg.sim, Scene.from_meshes(box, cfg.sim))
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    pats = _patterns(proj.width_px, proj.height_px)
    rng = np.random.default_rng(0)
    renderer.render(look_at((0, 0, 500), (0, 0, 0)), pats[0], cam.exposure_ms, 0.0, rng)  # warm caches (rays)
    frame, stack = [], []
    for i in range(repeat):
        pose = look_at((3.0 * i, 1.0, cfg.sensor.standoff_mm), (3.0 * i, 0.0, 0.0))
        t0 = time.perf_counter()
        renderer.render(pose, pats[1], cam.exposure_ms, 0.0, rng)  # new pose: ray cast + shading
        frame.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        renderer.render_stack(pose, pats, cam.exposure_ms, 0.0, rng)  # same pose: cached geometry
        stack.append(time.perf_counter() - t0)
    return {
        "cell": cell_file.name,
        "camera": f"{cam.width_px}x{cam.height_px}",
        "projector": f"{proj.width_px}x{proj.height_px}",
        "frame_new_pose_s": min(frame),
        "stack40_one_pose_s": min(stack),
        "per_pattern_ms": 1000 * min(stack) / len(pats),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--repeat", type=int, default=3, help="runs per measurement; the best is reported")
    args = ap.parse_args()
    rows = [bench(CELLS / name, args.repeat) for name in ("sim.yaml", "sim_hires.yaml")]
    machine = {"nproc": os.cpu_count(), "cpu": _cpu_model(), "python": platform.python_version()}
    if args.json:
        print(json.dumps({"machine": machine, "results": rows}, indent=2))
        return
    print(f"machine: {machine['nproc']} cores, {machine['cpu']}, Python {machine['python']}")
    print(
        f"{'cell':<16}{'camera':>11}{'projector':>11}{'frame, new pose (s)':>21}{'40-stack, 1 pose (s)':>22}"
        f"{'ms/pattern':>12}"
    )
    for r in rows:
        print(
            f"{r['cell']:<16}{r['camera']:>11}{r['projector']:>11}{r['frame_new_pose_s']:>21.3f}"
            f"{r['stack40_one_pose_s']:>22.3f}{r['per_pattern_ms']:>12.1f}"
        )


if __name__ == "__main__":
    main()
