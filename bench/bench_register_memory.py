"""Peak memory of the registration alone on a finished inspection's views (issue 16, item 5).

Reads a run folder (`cell inspect ... --out RUN`), loads its views as a resumed job does (the view store's
budget applies: the newest views' full points stay, the rest are read from their folders when needed),
refines them against each other, then runs the job's ``register`` (merge, alignment, uncertainty, error map)
and prints its wall and CPU seconds and the process's peak RSS before and during it (VmHWM, reset before the
registration through /proc/self/clear_refs). Run it under `/usr/bin/time -f "%M kB"` for the whole
process's peak as well; `--out FILE` writes the registration record as JSON with a hash of the registered
points, their deviations and u, to compare two versions'. `--scan` first does what the decode worker does as
each view arrives (the refinement's first overlaps, the maps' pairs, the merge bins), so the registration
starts from what a whole run holds, and prints what the job holds then, by part (numpy bytes).

    .venv/bin/python bench/bench_register_memory.py RUN [--scan] [--out registration.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_tail_steps import arrive_as_decoded, load_finished_run  # bench/ on sys.path (a script)

from cell.analysis._pose_kernel import pose_sigma


def status_kb(field: str) -> int:
    """A figure of /proc/self/status in kB (VmRSS, VmHWM)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def held_bytes(job: Any) -> dict[str, int]:
    """What the job holds by part (numpy bytes): the views' evaluation subsets, planes, decode u and KD-trees
    (indices and nodes: 72 bytes a node, scipy's ckdtreenode), full points held, hole regions; the
    refinement's pools and first matchings, the maps' pairs, the merge bins kept."""

    def nbytes(x: Any) -> int:
        if isinstance(x, np.ndarray):
            return int(x.nbytes)
        if isinstance(x, (tuple, list)):
            return sum(nbytes(y) for y in x)
        if isinstance(x, dict):
            return sum(nbytes(y) for y in x.values())
        if dataclasses.is_dataclass(x):
            return sum(nbytes(getattr(x, f.name)) for f in dataclasses.fields(x))
        return 0

    views = list(job.views._views.values())
    trees = [v.__dict__["eval_tree"] for v in views if "eval_tree" in v.__dict__]
    bins = job._merge_bins
    return {
        "evaluation points": sum(v.eval_W.nbytes for v in views),
        "planes": sum(nbytes(v.planes) for v in views),
        "evaluation u": sum(nbytes(v.eval_u) for v in views),
        "trees": sum(t.indices.nbytes + 72 * t.size for t in trees),
        "full points held": sum(v.held_bytes for v in views),
        "hole regions": sum(nbytes(r.boundary_W) + nbytes(r.points_W) for v in views for r in v.regions),
        "pools": sum(p._head.nbytes for p in job._overlaps._pools.values()),
        "first matchings": nbytes(list(job._overlaps._first.values())),
        "maps' pairs": nbytes(job._pairs._pairs),
        "merge bins": 0 if bins is None else sum(b.nbytes for b in bins._bins.values()),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, help="write the registration record (JSON) here")
    ap.add_argument("--scan", action="store_true", help="the decode worker's work per view first")
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    if args.scan:  # as the decode worker does (the last view's maps' pairs and bins are left to the tail)
        arrive_as_decoded(job, run)
        held = held_bytes(job)
        print(f"held after the scan: {sum(held.values()) / 1e6:.0f} MB: ", end="")
        print(", ".join(f"{k} {v / 1e6:.1f}" for k, v in held.items()))
    pose_sigma(np.ones((1, 1)), np.zeros((1, 6)), np.eye(6), None)  # loaded before the clock too
    done, _ = job.refinement(run)
    print(
        f"{len(done)} views loaded and refined: RSS {status_kb('VmRSS') / 1e6:.2f} GB, "
        f"peak so far {status_kb('VmHWM') / 1e6:.2f} GB"
    )
    Path("/proc/self/clear_refs").write_text("5")  # VmHWM from here on: the registration's own peak
    wall, cpu = time.perf_counter(), time.process_time()
    registration = job.register(run, checkpoint.views)
    print(
        f"register: {time.perf_counter() - wall:.1f} s wall, {time.process_time() - cpu:.1f} s CPU, "
        f"peak RSS {status_kb('VmHWM') / 1e6:.2f} GB ({status_kb('VmHWM')} kB), "
        f"{registration.get('n_points')} points of {registration.get('n_points_views')}"
    )
    if args.out:
        cloud = job._cloud
        if cloud is not None:  # the registered points, deviations and u, to the bit
            digest = hashlib.sha256(cloud.points_P.tobytes())
            for values in (
                cloud.uncertainty_mm,
                None if cloud.error_map is None else cloud.error_map.deviation_mm,
            ):
                digest.update(b"" if values is None else values.tobytes())
            registration = {**registration, "cloud_sha256": digest.hexdigest()}
        args.out.write_text(json.dumps(registration, indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
