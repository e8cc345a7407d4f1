"""How far the cell's believed camera poses are from the simulated world's, where it matters: on the part.

Reads the world's truth (the true arm and hand-eye), so it serves tests and benchmarks only, never cell/.
"""

from __future__ import annotations

import numpy as np

from cell.calibration import active_hand_eye
from cell.calibration.kinematics import KinematicErrors
from cell.calibration.procedures import camera_over, flange_for_camera
from cell.config import CellConfig
from cell.planning.kinematics import UR5E
from fakes.sim.world import World

# inspection-like views all around the demo part: (x, y) of the aim point on the table (mm), azimuth (deg)
VIEWS = (
    (200.0, -40.0, 0.0),
    (-200.0, 40.0, 180.0),
    (120.0, 60.0, 90.0),
    (150.0, 0.0, 0.0),
    (-150.0, 0.0, 180.0),
)


def part_error_spread(cfg: CellConfig, world: World, errors: KinematicErrors | None) -> float:
    """The largest distance (mm) from their mean of the errors of the point at the stand-off in front of the
    camera (on the part), between where ``cfg`` (its active hand-eye; ``errors``' arm, else the nominal one)
    believes it and where ``world`` puts it, over :data:`VIEWS` at 30 deg tilt. A common offset is the part's
    datums' to take; this rest moves views against each other."""
    q_home = np.deg2rad(cfg.robot.home_joints_deg)
    T_T_C, point = active_hand_eye(cfg), np.array([0.0, 0.0, cfg.sensor.standoff_mm, 1.0])
    errs = []
    for x, y, azimuth in VIEWS:
        T_W_C = camera_over(cfg, np.array([x, y, 40.0]), 30.0, azimuth)
        q = UR5E.ik_nearest(flange_for_camera(cfg, T_W_C), q_home)
        believed = (UR5E.fk(q) if errors is None else errors.flange(q)) @ T_T_C @ point
        errs.append((believed - world.true_flange(q) @ world.sensor.T_T_C.matrix() @ point)[:3])
    e = np.array(errs)
    return float(np.linalg.norm(e - e.mean(0), axis=1).max())
