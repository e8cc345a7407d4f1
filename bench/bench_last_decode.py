"""The decode of an inspection's last view, timed as the decode worker runs it after the last frame, and
checked against the view the run wrote.

Reads a finished run folder (`cell inspect ... --out RUN`, with the last view's raw stack kept), copies it
without its last view (and without the other views' raw stacks) into a scratch folder, makes every earlier
view arrive as the decode worker does (their first overlaps, feedback-map pairs and merge bins), then runs
``job.decode`` of the last view on its raw stack with the flange pose and joints of its ``view.json``
(``last=True``), ``--repeat`` times after one untimed warm-up: wall and CPU seconds of each, also until the
views' refinement is made (what the evaluation and the registration begin with; its T hashed), and of the
steps inside it (wall and thread CPU of their calls). The files it writes (points, defect regions, reasons
image, view.json) are compared with the run's own: a change that keeps the decode's results must print
"identical".

    .venv/bin/python bench/bench_last_decode.py RUN [--repeat 3] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import filecmp
import hashlib
import json
import os
import pstats
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from bench_tail_steps import load_finished_run  # bench/ is on sys.path when run as a script

import cell.inspection as inspection
from cell.inspection import Captured
from cell.inspection_run import open_inspection_run
from cell.view_files import RAW_IMAGES, load_raw_stack

COMPARED = ("points.npz", "defects.npz", "reasons.png", "view.json")
STEPS = (
    "decode",
    "link_cluster",
    "measured_normals",
    "unreliable_pixels",
    "view_uncertainty",
    "signed_distance",
    "voxel_subsample_index",
    "estimate_normals",
    "prepare_overlaps",
    "save_raw_stack",
    "save_view_points",
    "save_planes",
    "save_regions",
)


TIMES: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])


def timed(owner: Any, name: str, label: str | None = None) -> None:
    """Wrap ``owner.name`` so that its calls add to TIMES[label or name] (wall s, CPU s of the calling thread,
    calls): the steps run on two threads, so the process's CPU time would count the other's."""
    inner = getattr(owner, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        wall, cpu = time.perf_counter(), time.thread_time()
        try:
            return inner(*args, **kwargs)
        finally:
            entry = TIMES[label or name]
            entry[0] += time.perf_counter() - wall
            entry[1] += time.thread_time() - cpu
            entry[2] += 1

    setattr(owner, name, wrapper)


def same_file(a: Path, b: Path) -> bool:
    """Whether two view files hold the same: npz files array by array (their zip entries carry the time they
    were written), others byte by byte."""
    if a.suffix != ".npz":
        return filecmp.cmp(a, b, shallow=False)
    with np.load(a) as za, np.load(b) as zb:
        return sorted(za.files) == sorted(zb.files) and all(np.array_equal(za[k], zb[k]) for k in za.files)


def scratch_copy(run_dir: Path, last: int, into: Path) -> Path:
    """``run_dir`` copied into ``into`` without view ``last`` and without the other views' raw stacks."""
    target = into / run_dir.name
    skip = {f"{last:03d}"}

    def ignore(folder: str, names: list[str]) -> set[str]:
        if Path(folder) == run_dir / "views":
            return skip & set(names)
        return {RAW_IMAGES} & set(names) if Path(folder).parent == run_dir / "views" else set()

    shutil.copytree(run_dir, target, ignore=ignore)
    return target


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true", help="cProfile one decode (cumulative time, top 30)")
    args = ap.parse_args()
    source = open_inspection_run(args.run)
    last = source.completed_views()[-1]
    view_dir = source.view_dir(last)
    stack = load_raw_stack(view_dir)
    if stack is None:
        raise SystemExit(f"view {last} of {args.run} keeps no raw stack")
    meta = json.loads((view_dir / "view.json").read_text())
    with tempfile.TemporaryDirectory(prefix="bench-last-decode-") as scratch:
        copy = scratch_copy(args.run.resolve(), last, Path(scratch))
        run, job, checkpoint = load_finished_run(copy)
        for i in run.completed_views():
            job._first_overlaps(run, job.views.get(run, i))
            job.bin_arrived_view(run, job.views.get(run, i))
        view = checkpoint.views[last]

        def once() -> tuple[float, float, float, float]:
            captured = Captured(
                stack.copy(), np.asarray(meta["T_B_T"]), np.asarray(meta["joints_rad"]), "bench", last, True
            )
            job._refinement = None  # the views' refinement made again, as after the real last view
            wall, cpu = time.perf_counter(), time.process_time()
            with run.writing_view(last) as tmp:
                job.decode(view, captured, tmp)
            decoded = time.perf_counter() - wall, time.process_time() - cpu
            refined = job.refinement(run)[1]  # what the evaluation and the registration begin with
            took = (*decoded, time.perf_counter() - wall, time.process_time() - cpu)
            same = [n for n in COMPARED if same_file(view_dir / n, run.view_dir(last) / n)]
            T = hashlib.sha256(np.stack(refined.T).tobytes()).hexdigest()[:12]
            differ = sorted(set(COMPARED) - set(same))
            print(
                f"  decode of view {last}: {took[0]:.2f} s wall, {took[1]:.2f} s CPU; with the refinement "
                f"{took[2]:.2f} s wall, {took[3]:.2f} s CPU (T {T}); files "
                + (f"DIFFER: {differ}" if differ else "identical")
            )
            shutil.rmtree(run.view_dir(last))
            return took

        once()  # warm-up: the first call's imports and caches
        if args.profile:
            prof = cProfile.Profile()
            prof.enable()
            once()
            prof.disable()
            pstats.Stats(prof).sort_stats("cumulative").print_stats(30)
        for name in STEPS:
            timed(inspection, name, "decode (sensing)" if name == "decode" else name)
        timed(job, "_defects")
        timed(job, "_decode", "_decode (all but the wait for the writes)")
        TIMES.clear()
        took = np.array([once() for _ in range(args.repeat)])
        print(
            f"decode of view {last} ({stack.shape}): mean {took[:, 0].mean():.2f} s wall "
            f"(min {took[:, 0].min():.2f}), {took[:, 1].mean():.2f} s CPU (min {took[:, 1].min():.2f}); "
            f"with the refinement: mean {took[:, 2].mean():.2f} s wall (min {took[:, 2].min():.2f}), "
            f"{took[:, 3].mean():.2f} s CPU (min {took[:, 3].min():.2f}); load average {os.getloadavg()}"
        )
        print(f"  {'step (per decode)':32s} {'wall s':>8s} {'cpu s':>8s} calls")
        for name, (wall, cpu, calls) in TIMES.items():
            n = args.repeat
            print(f"  {name:32s} {wall / n:8.3f} {cpu / n:8.3f} {int(calls) // n}")


if __name__ == "__main__":
    main()
