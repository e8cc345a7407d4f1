"""The per-pixel sensor routine's d, S and alpha against the simulator's truth, over noise draws (the
routine's --seed), with the world's robot or one that lands exactly (docs/calibration.md, "In the honest
world, and the robot that held still").

Truth (bench code may read the world, cell/ may not): d = the true camera-projector baseline in the camera's
xy plane, S = the true camera's distance to the reference plane along its axis at the routine's pose,
alpha = the baseline's angle to the camera rows. Prints one JSON line for the truth, then one per seed: the
means over the encoded points, d's spread over them, and the routine's quality figure (height sigma).

    .venv/bin/python bench/trace_sensor_routine.py --cell recipes/cells/sim_binned_honest.yaml --seeds 1 2 3 \
        [--exact-robot] [--small] [--out DIR]

``--small``: the 160x120 rig of tests/test_calib_cli.py with its 6 x 4 mm steps and 256 points (about 12 s a
seed); otherwise the command's defaults (30 x 1 mm, 65536 points; ~200 s a seed on the binned camera).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import yaml

from cell.calibration.procedures import JointMotion
from cell.calibration.routines import run_routine
from cell.calibration.sensor_routines import SensorJob
from cell.config import load_cell_config
from cell.devices import build_devices
from cell.planning.kinematics import UR5E
from fakes.sim.testing import small_sensor


def cell_file(cell: Path, folder: Path, small: bool, exact: bool) -> Path:
    """``cell`` copied into ``folder``, with the small test sensor and/or a robot that lands exactly."""
    data = yaml.safe_load(cell.read_text())
    if small:
        sensor = small_sensor().model_dump(mode="json")
        sensor["T_T_C"] = data["sensor"]["T_T_C"]
        data["sensor"] = sensor
    if exact:
        data["world"].setdefault("robot", {})["repeatability_mm"] = 0.0
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def truth(cell: Path) -> dict[str, float]:
    """d, S, alpha of the world at the routine's reference pose (the robot moved there as the routine
    does)."""
    cfg = load_cell_config(cell)
    view = SensorJob(cfg).plan()[0]
    devices = build_devices(cfg, with_stage=True)
    robot, sim = devices.robot, devices.sim
    assert sim is not None, "a simulated cell is needed"
    robot.connect()
    for move in JointMotion(UR5E).plan(robot.tool_pose(), robot.joints(), view.T_B_T, None)[0]:
        robot.move_joint(move.target, 1.0, 2.0)
    T_W_C = sim.camera_pose()
    top = np.asarray(view.data["T_W_Bd"])[2, 3]
    t = sim.world.sensor.projector.T_C_P.matrix()[:3, 3]
    return {
        "d_mm": float(np.hypot(t[0], t[1])),
        "S_mm": float((top - T_W_C[2, 3]) / T_W_C[2, 2]),
        "alpha_deg": float(np.degrees(np.arctan2(t[1], t[0]))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell", type=Path, default=Path("recipes/cells/sim_binned_honest.yaml"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--exact-robot", action="store_true", help="repeatability 0: every landing exact")
    ap.add_argument("--small", action="store_true", help="tests/test_calib_cli.py's small rig and run")
    ap.add_argument("--out", type=Path, default=None, help="keep the run folders here")
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="trace_sensor_"))
    root.mkdir(parents=True, exist_ok=True)
    cell = cell_file(args.cell, root, args.small, args.exact_robot)
    print(json.dumps({"truth": truth(cell)}), flush=True)
    run = {"steps": 6, "step_mm": 4.0, "points": 256} if args.small else {}
    cfg = load_cell_config(cell)
    for seed in args.seeds:
        job = SensorJob(cfg, seed=seed, **run)
        figures = run_routine(job, root / f"seed{seed}", cell, seed=seed)["summary"]
        row = {k: round(figures[k]["mean"], 3) for k in ("d_mm", "S_mm", "alpha_deg")}
        row["d_std_mm"] = round(figures["d_mm"]["std"], 2)
        row["height_sigma_mm"] = round(figures["height_sigma_mm"]["mean"], 4)
        print(json.dumps({"seed": seed, **row}), flush=True)


if __name__ == "__main__":
    main()
