"""What the robot and the hand-eye alone do to VDI/VDE 2634 Part 3's SD (simulation bench: it reads the
world's truth, cell/ never does).

For each long-ball-bar position of Part 3 (cell/verification/multiview.py), the four views' flange targets are
planned as the verification job plans them, the joints are the IK solutions the calibration motion picks
(nearest the previous joints, from home), and each sphere centre is carried from the true camera pose (the
world's arm at those joints and its hand-eye) to the world through the pose the cell believes (its calibrated
kinematics and hand-eye). The mean over a sphere's two views is where the cell puts it; SD is their distance
minus the certified one. Sensor errors, noise and repeatability are left out: this is the poses' share.

    .venv/bin/python bench/multiview_pose_sd.py CAL/cell.yaml [...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cell.calibration import active_hand_eye, active_kinematics
from cell.calibration.procedures import flange_for_camera
from cell.config import load_cell_config
from cell.geometry import look_at
from cell.planning.kinematics import UR5E
from cell.verification.certificate import load_certificate
from cell.verification.multiview import BAR_DIRECTIONS_DEG, bar_pose, view_targets
from fakes.sim.world import build_world

CERTIFICATE = Path(__file__).resolve().parents[1] / "recipes" / "artefacts" / "certificate.yaml"


def predict(cell: Path) -> dict[str, float]:
    """Predicted Part 3 SD (um) per bar direction for the calibrated cell ``cell``."""
    cfg = load_cell_config(cell)
    world = build_world(cfg)
    errors, T_T_C = active_kinematics(cfg), active_hand_eye(cfg)
    T_W_B = cfg.robot.T_W_B.matrix()
    bar = load_certificate(CERTIFICATE).ball_bar_long
    assert bar is not None
    q = np.deg2rad(cfg.robot.home_joints_deg)
    out = {}
    for label, deg in BAR_DIRECTIONS_DEG.items():
        T_W_A = bar_pose(deg)
        L = bar.centre_distance_mm
        centres = [T_W_A[:3, :3] @ (s * L / 2, 0.0, 0.0) + T_W_A[:3, 3] for s in (-1, 1)]
        seen = []
        for k, target in enumerate(view_targets(T_W_A, L)):
            T_W_C = look_at(target + (0.0, 0.0, cfg.sensor.standoff_mm), target, up=(0.0, 1.0, 0.0))
            sols = UR5E.ik(flange_for_camera(cfg, T_W_C), q, allow_singular=False)
            q = sols.joints[int(np.argmin(np.abs(sols.joints - q).max(axis=1)))]
            flange = UR5E.fk(q) if errors is None else errors.flange(q)
            believed = T_W_B @ flange @ T_T_C
            true = T_W_B @ world.true_flange(q) @ world.sensor.T_T_C.matrix()
            c = np.append(centres[k // 2], 1.0)
            seen.append((believed @ np.linalg.inv(true) @ c)[:3])
        a, b = np.mean(seen[:2], axis=0), np.mean(seen[2:], axis=0)
        out[f"SD {label}"] = 1e3 * (float(np.linalg.norm(a - b)) - L)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cells", type=Path, nargs="+")
    args = ap.parse_args()
    for c in args.cells:
        print(c, {k: round(v, 1) for k, v in predict(c).items()})


if __name__ == "__main__":
    main()
