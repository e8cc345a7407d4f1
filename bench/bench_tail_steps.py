"""The steps of the work after the last frame, timed one by one on a finished inspection's views, and how far
the last view moves the others' refinement.

Reads a run folder (`cell inspect ... --out RUN`), prepares what the decode worker prepares while the robot
moves (each view's first overlaps and merge bins, in view order), then times, in one thread, the job's
``evaluate`` and ``register`` as the controller calls them after the last view, with each step inside them
(wall and CPU seconds; the process's numba kernels are loaded first so no compilation is counted). Then it
refines the views without the last one and prints how far each earlier view's correction moved when the last
view was added (the largest motion of its evaluation points between the two solutions, um): what an
incremental registration would have to correct after the last frame.

    .venv/bin/python bench/bench_tail_steps.py RUN
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

import cell.inspection as inspection
import cell.inspection_results as results
import cell.planning.feedback as feedback
from cell.analysis.errormap import signed_distance
from cell.geometry import transform_points
from cell.inspection import LambertianInspection
from cell.inspection_run import load_run_inputs, open_inspection_run
from cell.mesh import load_mesh
from cell.run_data import Checkpoint

TIMES: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])


def timed(owner: Any, name: str, label: str | None = None) -> None:
    """Wrap ``owner.name`` so that its calls add to TIMES[label or name] (wall s, CPU s, calls)."""
    inner = getattr(owner, name)
    label = label or name

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            entry = TIMES[label]
            entry[0] += time.perf_counter() - wall
            entry[1] += time.process_time() - cpu
            entry[2] += 1

    setattr(owner, name, wrapper)


def load_finished_run(path: Path) -> tuple[Any, LambertianInspection, Checkpoint]:
    """A finished inspection's run folder, its job (recipe, cell and nominal as the run read them) and its
    checkpoint, with the job's lazy models built and the error map's kernels loaded, so that no bench clock
    counts them (also used by bench_register_memory.py)."""
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}")
    run = open_inspection_run(path)
    recipe, cfg, _ = load_run_inputs(run)
    nominal_W = load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
    job = LambertianInspection(recipe, cfg, nominal_W)
    checkpoint = Checkpoint.from_json(run.load_checkpoint())
    signed_distance(job.nominal, np.zeros((4, 3)))  # the kernels loaded (or compiled) before the clock runs
    _ = job.plan_model, job.aligner, job.nominal_P
    return run, job, checkpoint


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    # what the decode worker did view by view (the last view's maps' pairs and bins are left to the tail)
    done = run.completed_views()
    for i in done:
        job._first_overlaps(run, job.views.get(run, i), pair_maps=i != done[-1])
        if i != done[-1]:
            job.bin_view(run, job.views.get(run, i))
    timed(inspection, "refine_views")
    timed(job.aligner, "align", "Aligner.align (evaluate, register)")
    timed(inspection, "signed_distance", "evaluate: deviations")
    timed(inspection, "covered_by_views", "evaluate: coverage")
    for name in ("accuracy_map", "uncertainty_map"):
        timed(feedback, name)
    for name in (
        "merge_bins",
        "registered_cloud_uncertainty",
        "held_redundant",
        "signed_distance",
    ):
        timed(results, name)
    timed(results.InspectionResults, "inspectable_coverage")
    for step, call in (
        ("evaluate", lambda: job.evaluate(run, checkpoint.views, checkpoint.iteration)),
        ("register", lambda: job.register(run, checkpoint.views)),
    ):
        wall, cpu = time.perf_counter(), time.process_time()
        call()
        print(f"{step}: {time.perf_counter() - wall:.2f} s wall, {time.process_time() - cpu:.2f} s CPU")
    print(f"  {'step':32s} {'wall s':>8s} {'cpu s':>8s} calls")
    for name, (wall, cpu, calls) in TIMES.items():
        print(f"  {name:32s} {wall:8.2f} {cpu:8.2f} {int(calls)}")
    moved_by_last(job, run)


def moved_by_last(job: LambertianInspection, run: Any) -> None:
    """How far each earlier view's refined pose moved when the last view was added (um, largest point)."""
    done, full = job.refinement(run)
    if len(done) < 3:
        return
    views = [job.views.get(run, i) for i in done]
    sigma = np.asarray(job._refinement[2]["prior_sigma_mm"]) if job._refinement else None
    sigma_deg = np.asarray(job._refinement[2]["prior_sigma_deg"]) if job._refinement else None
    if sigma is None or sigma_deg is None:
        return
    fewer = inspection.refine_views(
        [v.eval_W for v in views[:-1]],
        sigma[:-1],
        np.deg2rad(sigma_deg[:-1]),
        planes=[v.planes for v in views[:-1]],
        cameras=[v.camera_W for v in views[:-1]],
        trees=[v.eval_tree if len(v.eval_W) else None for v in views[:-1]],
        ids=list(done[:-1]),
        cache=job._overlaps,
    )
    um = []
    for a, b, v in zip(fewer.T, full.T[:-1], views[:-1], strict=True):
        if len(v.eval_W):
            gap = transform_points(a, v.eval_W) - transform_points(b, v.eval_W)
            um.append(1000 * float(np.linalg.norm(gap, axis=1).max()))
    print(f"adding view {done[-1]} moved the other views' refined poses by (um, per view): {np.round(um, 1)}")


if __name__ == "__main__":
    main()
