"""How well `cell calibrate all` recovers the honest world's errors, over a sweep of world seeds.

For each seed, recipes/cells/sim.yaml is copied with ``world.seed`` set (a different hand-eye, lens and
projector-pose error each time), `cell calibrate all` runs on it (the routines see the world only through the
simulated devices), and the results are compared here with the world's truth (fakes.sim.world.build_world:
bench code may read it, cell/ may not). Prints one row per seed and the worst case.

    .venv/bin/python bench/bench_calibration.py --seeds 1 2 3 4 5 [--out DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import yaml
from calibration_sd import predict_model
from multiview_pose_sd import predict as multiview_sd
from scipy.spatial.transform import Rotation

from cell.calibration import active_kinematics, active_sensor_config
from cell.calibration.handeye import pose_error
from cell.calibration.routines import calibrate_all
from cell.calibration.store import load_calibration
from cell.config import DEFAULT_CELL, load_cell_config
from cell.geometry import Pose, make_pose
from cell.planning.kinematics import UR5E
from fakes.sim.pose_truth import part_error_spread
from fakes.sim.world import build_world


def seeded_cell(seed: int, folder: Path) -> Path:
    """sim.yaml with its world drawn from ``seed`` (the camera noise too)."""
    data = yaml.safe_load(DEFAULT_CELL.read_text())
    data["world"]["seed"] = seed
    data["sim"]["seed"] = seed
    path = folder / f"sim_world{seed}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def camera_on_last_link(joint_zero_rad: float, d6_mm: float, T_T_C: Pose) -> Pose:
    """The camera in the frame of the arm's fifth link at joint 6 = 0: Rz(zero) Tz(d6) T_T_C (the UR's last DH
    link has a = alpha = 0). The last joint's zero and length move the camera exactly as a hand-eye rotation
    about and translation along the flange's z do, so no data separates them: this is the hand-eye a
    kinematic calibration can be held to."""
    return make_pose(Rotation.from_rotvec([0.0, 0.0, joint_zero_rad]).as_matrix(), [0.0, 0.0, d6_mm]) @ T_T_C


def compare(cell: Path, out: Path) -> dict[str, float]:
    """Recovered vs true values for one calibrated world."""
    cfg = load_cell_config(cell)
    world = build_world(cfg)
    true = world.sensor
    _, intr = load_calibration(out / "intrinsics" / "intrinsics.yaml", "camera_intrinsics")
    _, proj = load_calibration(out / "projector" / "projector.yaml", "projector")
    _, hand_eye = load_calibration(out / "kinematics" / "handeye.yaml", "hand_eye")
    T_true = true.T_T_C.matrix()
    calibrated = load_cell_config(out / "cell.yaml")
    active = active_sensor_config(calibrated).camera  # the lens adjusted with the projector, when it is
    row = {
        "camera_fx_err_pct": 100 * (active.fx_px / true.camera.fx_px - 1),
        "camera_cx_err_px": float(active.cx_px - true.camera.cx_px),
        "camera_routine_fx_err_pct": 100 * (intr["K"][0, 0] / true.camera.fx_px - 1),
        "projector_fx_err_pct": 100 * (proj["K"][0, 0] / true.projector.fx_px - 1),
        "projector_config_fx_err_pct": 100 * (cfg.sensor.projector.fx_px / true.projector.fx_px - 1),
    }
    row["T_C_P_err_mm"], row["T_C_P_err_deg"] = pose_error(proj["T_C_P"], true.projector.T_C_P.matrix())
    row["handeye_config_mm"], row["handeye_config_deg"] = pose_error(cfg.sensor.T_T_C.matrix(), T_true)
    row["handeye_mm"], row["handeye_deg"] = pose_error(hand_eye["T_T_C"], T_true)
    arm = active_kinematics(calibrated)
    if arm is not None:
        fitted = camera_on_last_link(arm.dq[5], UR5E.dh.d[5] + arm.dd[5], hand_eye["T_T_C"])
        truth = camera_on_last_link(world.joint_zero_rad[5], world.kinematics.dh.d[5], T_true)
        row["handeye_last_link_mm"], row["handeye_last_link_deg"] = pose_error(fitted, truth)
    row["part_error_spread_mm"] = part_error_spread(calibrated, world, active_kinematics(calibrated))
    row["part_error_spread_uncalibrated_mm"] = part_error_spread(cfg, world, None)
    validation = json.loads((out / "validate" / "validation.json").read_text())["summary"]
    row["plane_std_mm"] = validation["plane"]["std_mm"]
    row["plane_height_err_mm"] = validation["plane"]["height_error_mm"]
    row["sphere_radius_err_mm"] = validation["sphere"]["radius_error_mm"]
    part2 = predict_model(calibrated, world, active_sensor_config(calibrated))
    row["part2_sd_calibration_um"] = max((v for k, v in part2.items() if k.startswith("SD")), key=abs)
    row["part3_sd_poses_um"] = max(multiview_sd(out / "cell.yaml").values(), key=abs)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--out", type=Path, default=None, help="keep the calibration folders here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_calibration_"))
    root.mkdir(parents=True, exist_ok=True)
    rows = {}
    for seed in args.seeds:
        cell = seeded_cell(seed, root)
        t0 = time.perf_counter()
        calibrate_all(cell, root / f"world{seed}", seed=seed, say=lambda _: None)
        rows[seed] = {**compare(cell, root / f"world{seed}"), "seconds": time.perf_counter() - t0}
        if not args.json:
            print(f"seed {seed}: " + ", ".join(f"{k} {v:.4g}" for k, v in rows[seed].items()), flush=True)
    keys = next(iter(rows.values())).keys()
    worst = {k: max(abs(r[k]) for r in rows.values()) for k in keys}
    if args.json:
        print(json.dumps({"seeds": rows, "worst_abs": worst}, indent=2))
        return
    print("\n| figure | " + " | ".join(f"seed {s}" for s in rows) + " | worst abs |")
    print("|---|" + "---|" * (len(rows) + 1))
    for k in keys:
        print(f"| {k} | " + " | ".join(f"{r[k]:.4g}" for r in rows.values()) + f" | {worst[k]:.4g} |")


if __name__ == "__main__":
    main()
