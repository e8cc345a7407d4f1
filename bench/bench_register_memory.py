"""Peak memory of the registration alone on a finished inspection's views (issue 16, item 5).

Reads a run folder (`cell inspect ... --out RUN`), loads its views as a resumed job does (the view store's
budget applies: the newest views' full points stay, the rest are read from their folders when needed),
refines them against each other, then runs the job's ``register`` (merge, alignment, uncertainty, error map)
and prints its wall and CPU seconds and the process's peak RSS before and during it (VmHWM, reset before the
registration through /proc/self/clear_refs). Run it under `/usr/bin/time -f "%M kB"` for the whole
process's peak as well; `--out FILE` writes the registration record as JSON with a hash of the registered
points, their deviations and u, to compare two versions'.

    .venv/bin/python bench/bench_register_memory.py RUN [--out registration.json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
from bench_tail_steps import load_finished_run  # bench/ is on sys.path when run as a script

from cell.analysis._pose_kernel import pose_sigma


def status_kb(field: str) -> int:
    """A figure of /proc/self/status in kB (VmRSS, VmHWM)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, help="write the registration record (JSON) here")
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
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
