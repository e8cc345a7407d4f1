"""Hashes of a finished run's registration, to check that a change to the merge leaves it bit-identical.

Loads a run folder as bench_tail_steps.py does, bins the views as the decode worker does (``--bins eager``,
all but the last), on first ask (``lazy``, a resumed run) or keeps none (``none``: a budget of 0 bytes), then
registers and prints the SHA-256 of the cloud's points, deviations and u (and their counts), of the judged
cloud's figures and of the registration's record (as JSON), the held views' points cut and the views'
measured points per merge bin.

    .venv/bin/python bench/hash_register.py RUN [--bins eager|lazy|none]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_tail_steps import arrive_as_decoded, load_finished_run  # noqa: E402


def digest(x: np.ndarray | None) -> str:
    return "None" if x is None else hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--bins", choices=("eager", "lazy", "none"), default="eager")
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    if args.bins == "none":
        job.merge_bins_for(run).kept_bytes = 0  # each view's bins dropped as the next are added
    done = arrive_as_decoded(job, run, bins=args.bins == "eager")
    registration = job.register(run, checkpoint.views)
    refinement = registration.get("refinement", {})
    print(
        "unregistered views",
        refinement.get("unregistered_views"),
        "points dropped",
        refinement.get("unregistered_points_dropped"),
    )
    state = job.merge_bins_for(run)
    n_bins = {i: len(job._view_bins(job.views.get(run, i))[0]) for i in done}  # (binned again: not timed)
    per_bin = [state.n_points[i] / n_bins[i] for i in done if n_bins[i]]
    points, bins = sum(state.n_points[i] for i in done), sum(n_bins.values())
    print(
        f"points per bin (of {state.voxel_mm} mm): {points / bins:.3f} over the views,"
        f" {min(per_bin):.3f}-{max(per_bin):.3f} per view"
    )
    cloud = job._cloud
    assert cloud is not None and cloud.error_map is not None
    print(f"bins {args.bins}: {len(cloud.points_P)} points")
    print("points_P", digest(cloud.points_P))
    print("deviation_mm", digest(cloud.error_map.deviation_mm))
    print("uncertainty_mm", digest(cloud.uncertainty_mm))
    # what the verdict says of the points (its figures) and the registration's record, as report.json has them
    assert cloud.judged is not None
    for name, doc in (("figures", cloud.judged.figures()), ("registration", registration)):
        print(name, hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16])


if __name__ == "__main__":
    main()
