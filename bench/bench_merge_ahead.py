"""The registration after the last view with the earlier views' held-view cut and merge made ahead (issue 16,
item 2), against the registration in full: the same hashes, and what is left after the last view.

Loads a finished run as bench_tail_steps.py does (each view's first overlaps and merge bins made as the decode
worker makes them, all but the last's bins), refines the views as the registration does, then registers (a)
in full and (b) after :meth:`InspectionResults.merge_ahead` of all views but the last with the refinement's
corrections for them (as the refinement made ahead will give them), the last view unbinned before each, as
after its decode. Prints the hashes of both (as hash_register.py does: they must be equal), the wall and CPU
seconds of each registration and of its held-view cut and merge, and of the merge made ahead (one thread;
the first registration is a warm-up, then (a) and (b) ``--repeat`` times each, alternating).

    .venv/bin/python bench/bench_merge_ahead.py RUN [--repeat 2]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from bench_tail_steps import arrive_as_decoded, load_finished_run  # noqa: E402
from hash_register import digest  # noqa: E402

import cell.inspection_results as results  # noqa: E402
from cell.analysis.merge import HeldCut, load_kernels  # noqa: E402

TIMES: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])


def timed(owner: Any, name: str, label: str) -> None:
    """Wrap ``owner.name`` so that its calls add to TIMES[label] (wall s, CPU s)."""
    inner = getattr(owner, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            TIMES[label][0] += time.perf_counter() - wall
            TIMES[label][1] += time.process_time() - cpu

    setattr(owner, name, wrapper)


def hashes(job: Any, registration: dict[str, Any]) -> dict[str, str]:
    """The registered cloud's hashes, as hash_register.py prints them."""
    cloud = job._cloud
    assert cloud is not None and cloud.error_map is not None and cloud.judged is not None
    out = {
        "points_P": digest(cloud.points_P),
        "deviation_mm": digest(cloud.error_map.deviation_mm),
        "uncertainty_mm": digest(cloud.uncertainty_mm),
    }
    for name, doc in (("figures", cloud.judged.figures()), ("registration", registration)):
        out[name] = hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    arrive_as_decoded(job, run)
    load_kernels()
    done, refined = job.refinement(run)  # (made once: the registrations below find it made)
    n = len(done)
    held_before = [k for k in refined.unregistered if k < n - 1]
    print(f"views {done}, unregistered {[done[k] for k in refined.unregistered]}")
    state = job.merge_bins_for(run)
    timed(results, "held_redundant", "held cut (full)")
    timed(HeldCut, "with_last", "held cut (last view's share)")
    timed(results.MergeBins, "merge", "merge")

    def register(ahead: bool) -> tuple[dict[str, str], float, float, dict[str, list[float]]]:
        state.forget(done[-1])  # the last view unbinned, as after its decode (register bins it first)
        job._cloud = None
        if ahead:
            wall, cpu = time.perf_counter(), time.process_time()
            made = job.merge_ahead(run, done[:-1], refined.T[:-1], held_before)
            held = state._ahead
            print(
                f"  merge ahead of views {done[:-1]}: {'made' if made else 'NOT made'} in"
                f" {time.perf_counter() - wall:.3f} s wall, {time.process_time() - cpu:.3f} s CPU;"
                f" {0 if held is None else held.nbytes / 1e6:.1f} MB for"
                f" {sum(len(state._bins[i]) for i in done[:-1])} bins"
            )
        TIMES.clear()
        wall, cpu = time.perf_counter(), time.process_time()
        registration = job.register(run, checkpoint.views)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        return hashes(job, registration), wall, cpu, dict(TIMES)

    register(False)  # warm-up
    got: dict[str, list[Any]] = {"a": [], "b": []}
    for _ in range(args.repeat):
        for name in ("a", "b"):
            got[name].append(register(name == "b"))
    print(f"load average {os.getloadavg()}")
    for name, label in (("a", "(a) in full"), ("b", "(b) the earlier views merged ahead")):
        print(f"{label}: register after the last view")
        for _, wall, cpu, steps in got[name]:
            parts = ", ".join(f"{k} {w:.3f} s wall / {c:.3f} s CPU" for k, (w, c) in steps.items())
            print(f"  {wall:.3f} s wall, {cpu:.3f} s CPU; {parts}")
        walls, cpus = [r[1] for r in got[name]], [r[2] for r in got[name]]
        print(f"  median {statistics.median(walls):.3f} s wall, {statistics.median(cpus):.3f} s CPU")
        for key, value in got[name][0][0].items():
            print(f"  {key} {value}")
    same = all(r[0] == got["a"][0][0] for r in got["a"] + got["b"])
    print("hashes equal:", same)
    if not same:
        sys.exit(1)


if __name__ == "__main__":
    main()
