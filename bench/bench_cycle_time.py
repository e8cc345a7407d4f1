"""A simulated inspection's motion and capture phases beside the cycle-time limit of the views it visited, and
what follows the last frame.

Runs `cell inspect RECIPE --cell CELL` once (or reads a finished run folder, ``--run``), reads from the
journal which views were captured in which order (the plan and any re-planned views) and how long the
controller spent in the moving and capturing states, and prints them beside cell.planning.cycle_time's limit
for the same tour:
motion under the cell's TCP and joint limits at full speed (the controller runs at its speed fraction) and
capture at the display's frame period. Everything else the run spends (decoding, registration, reporting) is
the gap to the limit.

Then the tail: from the end of the last capture (the state change that follows the journal's last ``capture``
line) to the verdict's journal line (``verdict``; runs before it had one ``report`` line for the verdict and
the files together) and to the report's last file (``report_written``), with the time and, where the journal
has it (``cpu_s`` on state lines), the process's CPU seconds of each state on the way. On a shared machine
the CPU seconds are the steadier figure.

    .venv/bin/python bench/bench_cycle_time.py [--recipe recipes/pillar.yaml] [--cell recipes/cells/sim.yaml]
    .venv/bin/python bench/bench_cycle_time.py --run runs/pillar-...   # a run made before
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


def after_last_frame(entries: list[dict]) -> dict:
    """From the end of the last capture: seconds to the verdict line and to the report written, the views
    whose work was still pending then, and each state's wall (and CPU, when journalled) seconds."""
    last = max(k for k, e in enumerate(entries) if e["event"] == "capture")
    start = next(k for k in range(last + 1, len(entries)) if entries[k]["event"] == "state")
    t0 = entries[start]["t"]
    rest = entries[start:]

    def first(match) -> dict | None:
        return next((e for e in rest if match(e)), None)

    verdict = first(lambda e: e["event"] == "verdict" or (e["event"] == "report" and "verdict" in e))
    written = first(lambda e: e["event"] == "report_written") or (
        verdict if verdict is not None and verdict["event"] == "report" else None
    )
    states = [e for e in rest if e["event"] == "state"]
    phases = []
    for a, b in zip(states, states[1:]):
        cpu = b["cpu_s"] - a["cpu_s"] if "cpu_s" in a and "cpu_s" in b else None
        phases.append((a["state"], b["t"] - a["t"], cpu))
    return {
        "pending_views": sum(e["event"] == "view" for e in rest),
        "to_verdict_s": None if verdict is None else verdict["t"] - t0,
        "to_report_s": None if written is None else written["t"] - t0,
        "verdict": None if verdict is None else verdict.get("verdict"),
        "phases": phases,
    }


def print_tail(entries: list[dict]) -> None:
    tail = after_last_frame(entries)
    print(
        f"after the last frame ({tail['pending_views']} view(s) still being worked on then): verdict line "
        f"{tail['to_verdict_s']:.2f} s ({tail['verdict']}), report written {tail['to_report_s']:.2f} s"
    )
    print(f"  {'state':22s} {'wall s':>8s} {'cpu s':>8s}")
    for state, wall, cpu in tail["phases"]:
        print(f"  {state:22s} {wall:8.2f} {'-' if cpu is None else f'{cpu:.2f}':>8s}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--recipe", type=Path, default=REPO / "recipes" / "pillar.yaml")
    ap.add_argument("--cell", type=Path, default=REPO / "recipes" / "cells" / "sim.yaml")
    ap.add_argument("--run", type=Path, help="a finished run folder to read instead of running one")
    args = ap.parse_args()
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}")
    if args.run is not None:
        entries = journal_entries(args.run)
        cfg = load_cell_config(args.run / "inputs" / "cell.yaml")
        wall = entries[-1]["t"] - entries[0]["t"]
    else:
        cfg = load_cell_config(args.cell)
        with tempfile.TemporaryDirectory() as tmp:
            run = Path(tmp) / "run"
            t0 = time.perf_counter()
            cmd = [sys.executable, "-m", "cell", "inspect", str(args.recipe), "--cell", str(args.cell)]
            proc = subprocess.run([*cmd, "--out", str(run)], capture_output=True, text=True, cwd=REPO)
            wall = time.perf_counter() - t0
            if proc.returncode not in (0, 4, 5):  # pass, fail, incomplete: a judged run
                sys.exit(proc.stdout + proc.stderr)
            entries = journal_entries(run)
    print(f"load average at the end {os.getloadavg()}")
    seconds = state_seconds(entries)
    tour = visited_tour(entries)
    limit = cycle_time(cfg, tour, inspection_frames(cfg))
    moving, capturing = seconds.get("scanning_moving", 0.0), seconds.get("scanning_capturing", 0.0)
    print(f"{args.recipe.name} on {cfg.name}: {len(tour)} views captured, process wall {wall:.1f} s")
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
    print_tail(entries)


if __name__ == "__main__":
    main()
