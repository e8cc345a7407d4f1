"""Start-up time of the `cell` command: `cell --help`, each command's help and an immediate usage error.

Each command line runs as a fresh process ROUNDS times, interleaved; the median and best wall times are
printed with the load average. With `--base DIR` (a checkout of an older commit, e.g.
`git archive f94ac49 | tar -x -C /tmp/base`) the same lines run from that tree too, side by side.

    .venv/bin/python bench/bench_startup.py [--rounds 10] [--base /tmp/base]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LINES = [
    ["--help"],
    ["compare", "--help"],
    ["compare"],  # usage error: missing arguments
    ["plan", "--help"],
    ["scan", "--help"],
    ["glass", "--help"],
    ["devices", "--help"],
    ["docs", "--help"],
    ["sensor", "--help"],
    ["inspect", "--help"],
    ["calibrate", "--help"],
]


def once(tree: Path, args: list[str]) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cell", *args], cwd=tree, capture_output=True)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--base", type=Path, default=None, help="an older tree to compare with")
    args = ap.parse_args()
    trees = {"now": REPO} | ({"base": args.base} if args.base else {})
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}, {args.rounds} rounds")
    times = {(name, i): [] for name in trees for i in range(len(LINES))}
    for _ in range(args.rounds):
        for i, line in enumerate(LINES):
            for name, tree in trees.items():
                times[(name, i)].append(once(tree, line))
    head = "".join(f"{name + ' median/best s':>24s}" for name in trees)
    print(f"{'command line':26s}{head}")
    for i, line in enumerate(LINES):
        cols = "".join(f"{statistics.median(times[(n, i)]):>14.3f} / {min(times[(n, i)]):.3f}" for n in trees)
        print(f"{'cell ' + ' '.join(line):26s}{cols}")
    print(f"load average after {os.getloadavg()}")


if __name__ == "__main__":
    main()
