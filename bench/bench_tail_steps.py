"""The steps of the work after the last frame, timed one by one on a finished inspection's views, and how far
the last view moves the others' refinement.

Reads a run folder (`cell inspect ... --out RUN`), prepares what the decode worker prepares while the robot
moves (each view's first overlaps and merge bins, in view order), then times, in one thread, the job's
``evaluate`` and ``register`` as the controller calls them after the last view, with each step inside them
(wall and CPU seconds; the process's numba kernels are loaded first so no compilation is counted). The joint
refinement of the views before the last, which the run makes ahead while the robot moves to the last view, is
made before the clocks too, so ``refine_newest`` is what the refinement after the last frame costs. Then it
makes the joint refinement of all the views (what the refinement after the last frame was before it was made
incremental, timed alone) and prints how far each view's incremental correction is from it (the largest
motion of its evaluation points between the two, um), and how far the joint refinement of the views before
the last is from it (how far adding the last view moves the others in the joint solve).

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


def arrive_as_decoded(job: LambertianInspection, run: Any, bins: bool = True) -> list[int]:
    """What the decode worker did as each of the run's views arrived: its first overlaps and feedback maps'
    pairs and, with ``bins``, its merge bins; the last view's pairs and bins are left to the tail, as the
    plan's last view's decode leaves them. The completed views' indices."""
    done = run.completed_views()
    for i in done:
        job._first_overlaps(run, job.views.get(run, i), pair_maps=i != done[-1])
        if bins and i != done[-1]:
            job.bin_arrived_view(run, job.views.get(run, i))
    return done


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument(
        "--prefixes",
        type=int,
        default=3,
        help="also compare the incremental and joint refinement of the views up to each of this many views "
        "before the last (their newest registered, where the last is held)",
    )
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    done = arrive_as_decoded(job, run)
    if len(done) >= 3:  # made ahead, while the robot moves to the last view (LambertianInspection._joint)
        job._joint([job.views.get(run, i) for i in done[:-1]])
    timed(inspection, "refine_views")
    timed(inspection, "refine_newest")
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
    prefixes(job, run, args.prefixes)


def moved_by_last(job: LambertianInspection, run: Any) -> None:
    """The joint refinement of all views, timed, and how far from it (um, largest point per view) each view's
    incremental correction is, and each earlier view's correction in the joint refinement without the last
    view."""
    done, incremental = job.refinement(run)
    if len(done) < 3 or job._older is None:
        return
    views = [job.views.get(run, i) for i in done]
    sigma, _ = job._prior(views)
    wall, cpu = time.perf_counter(), time.process_time()
    joint = inspection.refine_views(
        [v.eval_W for v in views], sigma[:, 0], sigma[:, 1], **job.refine_inputs(views)
    )
    print(
        f"joint refinement of all {len(done)} views (first matchings made): "
        f"{time.perf_counter() - wall:.2f} s wall, {time.process_time() - cpu:.2f} s CPU"
    )

    def apart(A: list[Any], B: list[Any]) -> list[float]:
        return [
            1000
            * float(
                np.linalg.norm(transform_points(a, v.eval_W) - transform_points(b, v.eval_W), axis=1).max()
            )
            for a, b, v in zip(A, B, views, strict=False)
            if len(v.eval_W)
        ]

    for name, found in (("incremental", incremental), ("joint", joint)):
        print(
            f"  {name:12s} rms {found.rms_before_mm:.4f} -> {found.rms_after_mm:.4f} mm, "
            f"unregistered {[done[k] for k in found.unregistered]}"
        )
    print(f"incremental vs joint of all (um, per view): {np.round(apart(incremental.T, joint.T), 1)}")
    older = job._older[1]
    print(
        f"adding view {done[-1]} moved the other views' joint refined poses by (um, per view): "
        f"{np.round(apart(older.T, joint.T[:-1]), 1)}"
    )


def prefixes(job: LambertianInspection, run: Any, count: int) -> None:
    """For the views up to each of the ``count`` views before the last: the newest view refined alone against
    the joint refinement of the ones before it (:func:`refine_newest`) against the joint refinement of them
    all, the largest difference of a view's points (um, per view) and the newest view's correction (um)."""
    done = run.completed_views()
    for m in range(len(done) - 1, max(len(done) - 1 - count, 2), -1):
        views = [job.views.get(run, i) for i in done[:m]]
        sigma, _ = job._prior(views)

        points = [v.eval_W for v in views]
        older = inspection.refine_views(
            points[:-1], *job._prior(views[:-1])[0].T, **job.refine_inputs(views[:-1])
        )
        cpu = time.process_time()
        inputs = job.refine_inputs(views)
        newest = inspection.refine_newest(older, points, sigma[-1, 0], sigma[-1, 1], **inputs)
        newest_cpu = time.process_time() - cpu
        joint = inspection.refine_views(points, sigma[:, 0], sigma[:, 1], **inputs)
        if newest is None:
            print(f"views {done[0]}..{done[m - 1]}: the newest view's pairs change the held views: joint")
            continue
        um = [
            1000 * float(np.linalg.norm(transform_points(a, p) - transform_points(b, p), axis=1).max())
            for a, b, p in zip(newest.T, joint.T, points, strict=True)
            if len(p)
        ]
        moved = 1000 * newest.correction_mm(points)[-1]
        print(
            f"views {done[0]}..{done[m - 1]} (newest {done[m - 1]} corrected by {moved:.1f} um, "
            f"{newest_cpu:.2f} s CPU; unregistered {[done[k] for k in newest.unregistered]} vs joint "
            f"{[done[k] for k in joint.unregistered]}): incremental vs joint (um, per view) {np.round(um, 1)}"
        )


if __name__ == "__main__":
    main()
