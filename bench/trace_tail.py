"""Where the time after the last frame goes: a `cell` command run in-process (e.g. `demo`) with timers on the
tail's steps, then a per-thread timeline of every timed call that ended after the last capture (seconds from
its end; wall and the thread's own CPU). Each step is timed where the pipeline calls it, so the threads that
run side by side (the decode worker, the refinement made ahead, the evaluation, the registration's pool) show
as they overlap. The timers cost a little: the verdict comes ~0.1-0.3 s later than in `bench_cycle_time.py`.

    .venv/bin/python bench/trace_tail.py demo
"""

from __future__ import annotations

import atexit
import functools
import importlib
import sys
import threading
import time
from typing import Any

# thread, step, start, end (perf_counter), thread CPU, the process's CPU at the start and at the end
EVENTS: list[tuple[str, str, float, float, float, float, float]] = []
STEPS = [  # (module, attribute as the caller looks it up, label)
    ("cell.inspection", "LambertianInspection.capture", "capture"),
    ("cell.inspection", "LambertianInspection.decode", "decode"),
    ("cell.inspection", "LambertianInspection._first_overlaps", "first overlaps"),
    ("cell.inspection", "refine_views", "refine_views"),
    ("cell.inspection", "refine_newest", "refine_newest"),
    ("cell.inspection", "LambertianInspection.evaluate", "evaluate"),
    ("cell.inspection", "LambertianInspection._evaluation_alignment", "evaluate: alignment"),
    ("cell.inspection", "LambertianInspection._measured", "evaluate: deviations"),
    ("cell.inspection", "LambertianInspection._covered", "evaluate: coverage"),
    ("cell.planning.feedback", "accuracy_map", "evaluate: accuracy map"),
    ("cell.planning.feedback", "uncertainty_map", "evaluate: uncertainty map"),
    ("cell.view_files", "save_raw_stack", "raw images"),
    ("cell.inspection", "save_raw_stack", "raw images"),
    ("cell.inspection_results", "InspectionResults.register", "register"),
    ("cell.inspection_results", "held_redundant", "register: held-view cut"),
    ("cell.inspection_results", "merge_bins", "register: merge"),
    ("cell.analysis.merge", "HeldCut.with_last", "register: held-view cut, the last view's share"),
    ("cell.analysis.merge", "PartialMerge.finish", "register: merge, the last view's share"),
    ("cell.inspection_results", "InspectionResults.merge_ahead", "cut and merge ahead of the last view"),
    ("cell.analysis.view_refinement", "ViewRefinement.to_json", "register: refinement's record"),
    ("cell.inspection_results", "InspectionResults._aligned", "register: alignment + stored points"),
    ("cell.analysis.alignment", "Aligner.align", "alignment (Aligner.align)"),
    ("cell.inspection_results", "stored_points", "register: stored points"),
    ("cell.inspection_results", "signed_distance", "register: error map"),
    ("cell.inspection_results", "InspectionResults.inspectable_coverage", "register: coverage"),
    ("cell.inspection_results", "table_seam", "register: table seam"),
    ("cell.inspection_results", "registered_cloud_uncertainty", "register: u"),
    ("cell.inspection_results", "default_link_radius", "register: link radius"),
    ("cell.analysis.uncertainty", "CloudUncertainty.budget", "register: u budget"),
    ("cell.inspection_results", "InspectionResults._judge", "register: judge"),
    ("cell.analysis.report", "point_figures", "register: judge: figures"),
    ("cell.inspection_results", "InspectionResults.report", "report (the verdict)"),
]


def timed(module: str, attribute: str, label: str) -> None:
    """Wrap ``module.attribute`` (a function or Class.method) so that each call adds to EVENTS (nothing when
    the code timed has no such attribute: the same steps time an older version)."""
    owner: Any = importlib.import_module(module)
    *path, name = attribute.split(".")
    for part in path:
        owner = getattr(owner, part)
    f = getattr(owner, name, None)
    if f is None:
        return

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start, cpu, process = time.perf_counter(), time.thread_time(), time.process_time()
        try:
            return f(*args, **kwargs)
        finally:
            end = time.perf_counter()
            thread = threading.current_thread().name
            EVENTS.append((thread, label, start, end, time.thread_time() - cpu, process, time.process_time()))

    setattr(owner, name, wrapper)


def timeline() -> None:
    """Print the calls that ended after the last capture ended, by start, and the CPU the whole process
    spent (all threads) from the last frame to the verdict: on two cores the tail cannot be shorter than
    half of it."""
    captures = [e for e in EVENTS if e[1] == "capture"]
    if not captures:
        print("no capture was timed")
        return
    last_capture = max(captures, key=lambda e: e[3])
    last = last_capture[3]
    print("after the last frame (s from its end)    thread              start ->    end   wall    cpu")
    for thread, label, start, end, cpu, _, _ in sorted(EVENTS, key=lambda e: e[2]):
        if end >= last and label != "capture":
            span = f"{start - last:6.2f} -> {end - last:6.2f}"
            print(f"  {label:38s} {thread:18s} {span}  {end - start:5.2f}  {cpu:5.2f}")
    verdicts = [e for e in EVENTS if e[1] == "report (the verdict)" and e[2] >= last]
    if verdicts:
        verdict = verdicts[0]
        cpu = verdict[5] - last_capture[6]
        wall = verdict[2] - last
        print(f"process CPU from the last frame to the verdict: {cpu:.2f} s in {wall:.2f} s", end="")
        print(f" ({cpu / wall:.2f} cores)")


def main() -> None:
    for spec in STEPS:
        timed(*spec)
    from cell.cli import main as cell_main

    atexit.register(timeline)
    cell_main(sys.argv[1:])


if __name__ == "__main__":
    main()
