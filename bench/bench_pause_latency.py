"""Pause latency mid-move in the simulated cell: SIGTERM (what `kill`, systemd and docker stop send) arrives
while the arm moves; how long until the stop begins, and until the arm stands still?

The simulated arm of recipes/cells/sim.yaml runs on wall-clock time here (robot.options.sim_realtime_factor
= 1), so a signal lands mid-move as it would on the real cell. The handler does what the controller's does
(`Controller.request_pause` -> `robot.stop()`); the move polls every 4 ms and decelerates from the speed it
has at the request, at the configured maximum acceleration (stopL). Target (issue 13): the stop begins within
100 ms of the request. The time to stand still adds the ramp v/a, set by the robot config, not by software.

    .venv/bin/python bench/bench_pause_latency.py [--trials 10]
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import threading
import time

import numpy as np

from cell.config import DEFAULT_CELL, RobotConfig, load_cell_config
from cell.errors import MotionStopped
from cell.planning.kinematics import UR5E
from fakes.clock import SimClock
from fakes.robot import SimRobot


def one_trial(cfg: RobotConfig, rng: np.random.Generator) -> dict[str, float]:
    robot = SimRobot(cfg, clock=SimClock())
    robot.connect()
    start = UR5E.fk(np.deg2rad(cfg.home_joints_deg))
    target = start.copy()
    target[:3, 3] += (0.0, 150.0, -150.0)  # a 212 mm view-to-view move, straight, same orientation
    v, a = 0.8 * cfg.max_tcp_speed_mm_s, 0.8 * cfg.max_tcp_accel_mm_s2  # the controller's speed fraction
    marks: dict[str, float] = {}

    def on_sigterm(*_: object) -> None:
        marks["handler"] = time.monotonic()
        marks["sim_request"] = robot.clock.now()
        robot.stop()

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    delay = float(rng.uniform(0.3, 0.9))  # somewhere in the cruise (the move lasts ~1.3 s)

    def send() -> None:
        marks["sent"] = time.monotonic()
        os.kill(os.getpid(), signal.SIGTERM)

    timer = threading.Timer(delay, send)
    timer.start()
    try:
        robot.move_linear(target, v, a)
        raise RuntimeError("the move ended before the signal: lengthen it")
    except MotionStopped:
        marks["still"] = time.monotonic()
    finally:
        timer.join()
        signal.signal(signal.SIGTERM, previous)
    entry = next(e for e in robot.command_log if e["command"] == "move_linear")
    sim_stop_begins = marks[
        "sim_request"
    ]  # the ramp starts at the request's sim instant (see fakes/robot.py)
    return {
        "signal_to_handler_ms": 1e3 * (marks["handler"] - marks["sent"]),
        "signal_to_still_ms": 1e3 * (marks["still"] - marks["sent"]),
        "ramp_ms": 1e3 * (entry["start_s"] + entry["duration_s"] - sim_stop_begins),
        "ramp_expected_ms": 1e3 * v / cfg.max_tcp_accel_mm_s2,
        "software_ms": 1e3 * (marks["still"] - marks["sent"]) - 1e3 * v / cfg.max_tcp_accel_mm_s2,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=10)
    args = parser.parse_args()
    cfg = load_cell_config(DEFAULT_CELL).robot
    cfg = cfg.model_copy(update={"options": {**cfg.options, "sim_realtime_factor": 1.0}})
    rng = np.random.default_rng(0)
    rows = [one_trial(cfg, rng) for _ in range(args.trials)]
    print(f"{args.trials} trials, SIGTERM mid-move, simulated UR5e of {DEFAULT_CELL.name} in wall-clock time")
    for key in ("signal_to_handler_ms", "software_ms", "ramp_ms", "ramp_expected_ms", "signal_to_still_ms"):
        values = [r[key] for r in rows]
        print(f"  {key:22s} median {statistics.median(values):7.1f}   max {max(values):7.1f}")
    print("  software_ms = signal to standstill minus the ramp (upper bound); target 100 ms")


if __name__ == "__main__":
    main()
