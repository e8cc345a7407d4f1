"""A simulated inspection's motion and capture phases beside the cycle-time limit of the views it visited.

Runs `cell inspect RECIPE --cell CELL` once, reads from the journal which views were captured in which order
(the plan and any re-planned views) and how long the controller spent in the moving and capturing states, and
prints them beside cell.planning.cycle_time's limit for the same tour: motion under the cell's TCP and joint
limits at full speed (the controller runs at its speed fraction) and capture at the display's frame period.
Everything else the run spends (decoding, registration, reporting) is the gap to the limit.

    .venv/bin/python bench/bench_cycle_time.py [--recipe recipes/pillar.yaml] [--cell recipes/cells/sim.yaml]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from cell.config import load_cell_config
from cell.planning.cycle_time import cycle_time, inspection_frames

REPO = Path(__file__).resolve().parent.parent


def journal_entries(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "journal.jsonl").read_text().splitlines() if line.strip()]


def state_seconds(entries: list[dict]) -> dict[str, float]:
    """Seconds in each controller state (full names, e.g. scanning_moving), from the time-stamped journal."""
    states = [(e["t"], e["state"]) for e in entries if e["event"] == "state"]
    out: dict[str, float] = defaultdict(float)
    for (t, state), (t_next, _) in zip(states, states[1:] + [(entries[-1]["t"], "")]):
        out[state] += t_next - t
    return dict(out)


def visited_tour(entries: list[dict]) -> list[np.ndarray]:
    """Flange poses T_B_T of the captured views, in capture order."""
    views: list[dict] = []
    for e in entries:
        if e["event"] in ("plan", "replan"):
            views.extend(e["views"])
    order = [e["view"] for e in entries if e["event"] == "capture"]
    return [np.asarray(views[i]["T_B_T"], dtype=np.float64) for i in order]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--recipe", type=Path, default=REPO / "recipes" / "pillar.yaml")
    ap.add_argument("--cell", type=Path, default=REPO / "recipes" / "cells" / "sim.yaml")
    args = ap.parse_args()
    cfg = load_cell_config(args.cell)
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "cell", "inspect", str(args.recipe), "--cell", str(args.cell)]
        proc = subprocess.run([*cmd, "--out", str(run)], capture_output=True, text=True, cwd=REPO)
        wall = time.perf_counter() - t0
        if proc.returncode:
            sys.exit(proc.stdout + proc.stderr)
        entries = journal_entries(run)
    seconds = state_seconds(entries)
    tour = visited_tour(entries)
    limit = cycle_time(cfg, tour, inspection_frames(cfg))
    moving, capturing = seconds.get("scanning_moving", 0.0), seconds.get("scanning_capturing", 0.0)
    print(f"{args.recipe.name} on {args.cell.name}: {len(tour)} views captured, process wall {wall:.1f} s")
    print(f"{'phase':28s} {'limit s':>9s} {'simulated run s':>16s}")
    print(f"{'motion (home, views, home)':28s} {limit.motion_s:9.2f} {moving:16.2f}")
    print(f"{'capture':28s} {limit.capture_s:9.2f} {capturing:16.2f}")
    print(f"{'motion + capture':28s} {limit.total_s:9.2f} {moving + capturing:16.2f}")
    other = {
        k: round(v, 2)
        for k, v in sorted(seconds.items())
        if k not in ("scanning_moving", "scanning_capturing")
    }
    print(f"other states of the run (s): {other}")
    print(limit.summary())


if __name__ == "__main__":
    main()
