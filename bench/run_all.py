"""Run every benchmark of bench/ in turn (what `make bench` does); each prints its own table.

Peers (Open3D, libigl, point-cloud-utils) are optional: install bench/requirements-peers.txt to include them.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHES = [
    "bench_startup.py",
    "bench_render.py",
    "bench_decode.py",
    "bench_plan.py",
    "bench_errormap.py",
    "bench_glass.py",
    "bench_inspect.py",
    "bench_sync.py",
    "bench_cycle_time.py",
    "bench_compare.py",
]


def main() -> int:
    failed = []
    for name in BENCHES:
        print(f"\n=== {name}", flush=True)
        if subprocess.run([sys.executable, str(HERE / name)], cwd=HERE.parent).returncode != 0:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
