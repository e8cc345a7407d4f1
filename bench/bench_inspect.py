"""Wall time of the full simulated demo inspection, the share of each phase, and the pipelining gain.

Runs `cell inspect recipes/pillar.yaml` on the default simulated cell (1024x768, the dissertation's prototype)
twice -- decoding overlapped with the next move and capture (the default), and strictly sequential -- and
reads the phase durations from each run's journal (state changes are time-stamped).

    .venv/bin/python bench/bench_inspect.py [--cell recipes/cells/sim.yaml] [--json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def phase_seconds(journal: Path) -> dict[str, float]:
    """Seconds spent in each top-level phase, from consecutive state entries of the journal."""
    entries = [json.loads(line) for line in journal.read_text().splitlines() if line.strip()]
    states = [(e["t"], e["state"].split("_")[0]) for e in entries if e["event"] == "state"]
    end = entries[-1]["t"]
    out: dict[str, float] = defaultdict(float)
    for (t, state), (t_next, _) in zip(states, states[1:] + [(end, "")]):
        out[state] += t_next - t
    return dict(out)


def run(cell: Path, pipelining: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        flag = "--pipelining" if pipelining else "--no-pipelining"
        t0 = time.perf_counter()
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "cell",
                "inspect",
                str(REPO / "recipes" / "pillar.yaml"),
                "--cell",
                str(cell),
                "--out",
                str(out),
                flag,
            ],
            capture_output=True,
            text=True,
            cwd=REPO,
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(proc.stdout + proc.stderr)
        doc = json.loads((out / "results" / "report.json").read_text())
        checkpoint = json.loads((out / "checkpoint.json").read_text())
        return {
            "pipelining": pipelining,
            "wall_s": wall,
            "phases_s": phase_seconds(out / "journal.jsonl"),
            "views": len(checkpoint["views"]),
            "verdict": doc["verdict"],
            "n_points": doc["n_points"],
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cell", type=Path, default=REPO / "recipes" / "cells" / "sim.yaml")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    results = [run(args.cell, True), run(args.cell, False)]
    if args.json:
        print(json.dumps(results, indent=2))
        return
    print(f"cell {args.cell.relative_to(REPO)}; {results[0]['views']} views; verdict {results[0]['verdict']}")
    phases = sorted(
        {p for r in results for p in r["phases_s"]}, key=lambda p: -results[0]["phases_s"].get(p, 0)
    )
    print(
        f"{'phase':<14}" + "".join(f"{'pipelined' if r['pipelining'] else 'sequential':>14}" for r in results)
    )
    for p in phases:
        print(f"{p:<14}" + "".join(f"{r['phases_s'].get(p, 0.0):>13.1f}s" for r in results))
    print(f"{'wall (process)':<14}" + "".join(f"{r['wall_s']:>13.1f}s" for r in results))
    print(f"pipelining gain: {results[1]['wall_s'] / results[0]['wall_s']:.2f}x")


if __name__ == "__main__":
    main()
