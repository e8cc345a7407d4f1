"""The evaluation after the last view alone, step by step: a finished inspection's views prepared as the
decode worker leaves them (each view's first overlaps and, but for the last view's, its maps' pairs), the
refinement made (as the refinement ahead has it when the evaluation needs it), then the job's ``evaluate``
called ``--repeat`` times, each as after the last frame (the moved points and the last view's pairs dropped
first). Prints each call's wall, thread CPU and process CPU (the error map's pool included), the thread CPU
(and wall) of each step, and a hash of what the evaluation decided (covered samples, IA, IU) with its figures,
so that two versions can be compared for identity.

    .venv/bin/python bench/bench_evaluate.py RUN [--repeat 3]
"""

from __future__ import annotations

import argparse
import hashlib
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from bench_tail_steps import arrive_as_decoded, load_finished_run  # bench/ on sys.path (a script)

import cell.inspection as inspection
import cell.planning.feedback as feedback

STEPS: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])  # thread CPU s, wall s


def timed(owner: Any, name: str, label: str) -> None:
    """Wrap ``owner.name`` so that its calls add their thread CPU and wall to STEPS[label]."""
    inner = getattr(owner, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        cpu, wall = time.thread_time(), time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            STEPS[label][0] += time.thread_time() - cpu
            STEPS[label][1] += time.perf_counter() - wall

    setattr(owner, name, wrapper)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    done = arrive_as_decoded(job, run, bins=False)
    job.refinement(run)
    job_class = inspection.LambertianInspection
    for name, label in (
        ("_pair_maps", "the last view's pairs"),
        ("_evaluation_alignment", "alignment"),
        ("_measured", "deviations"),
        ("_covered", "coverage"),
    ):
        timed(job_class, name, label)
    timed(feedback, "accuracy_map", "accuracy map")
    timed(feedback, "uncertainty_map", "uncertainty map")
    points = sum(len(job.views.get(run, i).eval_W) for i in done)
    print(f"{len(done)} views, {points} evaluation points")
    for _ in range(args.repeat):
        job._moved.clear()
        job._pairs.forget(done[-1])
        STEPS.clear()
        wall, cpu, process = time.perf_counter(), time.thread_time(), time.process_time()
        evaluation = job.evaluate(run, checkpoint.views, checkpoint.iteration)
        wall, cpu = time.perf_counter() - wall, time.thread_time() - cpu
        process = time.process_time() - process
        steps = ", ".join(f"{k} {c:.3f} ({w:.2f})" for k, (c, w) in STEPS.items())
        print(f"evaluate {wall:.2f} s wall, {cpu:.3f} thread CPU, {process:.3f} process CPU; steps: {steps}")
    ev = evaluation.state.evaluation
    digest = hashlib.sha256()
    for array in (ev.covered, ev.ia, ev.iu):
        digest.update(np.ascontiguousarray(array).tobytes())
    print(f"qualified {evaluation.qualified}, Q {ev.q!r}, {evaluation.figures}")
    print(f"covered, IA ({len(ev.ia)} points), IU ({len(ev.iu)} points): {digest.hexdigest()[:16]}")


if __name__ == "__main__":
    main()
