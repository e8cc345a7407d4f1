"""``cell scan`` in a simulated cell: bring the devices up, move the robot so the camera looks at the part
from a pose, scan one view (:func:`cell.sensing.scan.scan_view`) and write cloud.ply, masks.png and scan.json.

A run-level module beside :mod:`cell.inspection_run`: it builds devices (cell.devices) and moves the robot,
which the sensing package below it never does.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.errors import ConfigError
from cell.geometry import invert, look_at, pose_to_xyz_rotvec, transform_points
from cell.planning.kinematics import UR5E
from cell.sensing.patterns import gcps_baseline_patterns
from cell.sensing.scan import MASK_COLOURS, masks_image, scan_view, write_ply
from cell.sensing.triangulate import PinholeTriangulator, reference_model_from_geometry

CODECS = ("gcls", "gcps")
MODELS = ("pinhole", "reference")


def auto_pose(part_W: trimesh.Trimesh | None, standoff_mm: float) -> NDArray[np.float64]:
    """T_W_C looking straight down at the part's bounding-box centre (or the world origin) from the
    stand-off."""
    centre = part_W.bounds.mean(axis=0) if part_W is not None else np.zeros(3)
    return look_at(centre + (0.0, 0.0, standoff_mm), centre, up=(0.0, 1.0, 0.0))


def scan_in_cell(
    cell: Path,
    part_path: Path | None,
    T_W_C: NDArray[np.float64] | None,
    codec: str,
    model: str,
    out: Path,
    seed: int | None = None,
) -> dict[str, Any]:
    """``cell scan``: scan ``part_path`` (world mm; None: the empty table) in the simulated cell of config
    ``cell`` from camera pose ``T_W_C`` (None: :func:`auto_pose`) with ``codec`` (gcls or gcps) and the
    ``model`` triangulation (pinhole or reference). It triangulates with the cell config's sensor geometry,
    the simulator's own, not with a calibration: a check of the sensing chain, not a measurement. Writes
    cloud.ply (world mm, placed by where the cell believes the camera is), masks.png and scan.json (timings,
    counts per reason, poses) to ``out``; returns the scan.json content."""
    from cell.calibration import active_hand_eye, believed_flange
    from cell.calibration.active import active_measuring_patterns
    from cell.config import load_cell_config
    from cell.devices import build_devices, ready_to_capture
    from cell.mesh import load_mesh

    if codec not in CODECS:
        raise ConfigError(f"--codec: unknown codec '{codec}'; use gcls or gcps", field="--codec")
    if model not in MODELS:
        raise ConfigError(f"--model: unknown model '{model}'; use {' or '.join(MODELS)}", field="--model")
    cfg = load_cell_config(cell)
    t0 = time.perf_counter()
    if cfg.sensor.camera.driver != "sim":
        raise ConfigError(
            "cell scan checks the simulated sensing chain: it triangulates with the cell config's nominal "
            "sensor geometry, which only the simulator matches; use a cell whose drivers are all 'sim' (a "
            "real sensor measures through `cell inspect` with its calibration)",
            field="sensor.camera.driver",
        )
    part_W = load_mesh(part_path) if part_path is not None else None
    if T_W_C is None:
        T_W_C = auto_pose(part_W, cfg.sensor.standoff_mm)
    dev = build_devices(cfg, part_W=part_W, seed=seed)
    cam_cfg, proj_cfg = cfg.sensor.camera, cfg.sensor.projector
    with ready_to_capture(dev, cam_cfg):
        T_B_T = invert(cfg.robot.T_W_B.matrix()) @ T_W_C @ invert(cfg.sensor.T_T_C.matrix())
        # A joint move: a straight line from home may pass the base axis; IK picks the branch nearest to now.
        q = UR5E.ik_nearest(T_B_T, dev.robot.joints())
        dev.robot.move_joint(q, cfg.robot.max_joint_speed_rad_s, cfg.robot.max_joint_accel_rad_s2)
        # where the cell believes the camera is: the flange pose (calibrated kinematics when the cell has
        # them) through the active hand-eye (what a real cell knows; the simulator's true camera pose is not
        # the pipeline's to read)
        T_W_C_reported = cfg.robot.T_W_B.matrix() @ believed_flange(cfg, dev.robot) @ active_hand_eye(cfg)
        patterns = active_measuring_patterns(cfg) if codec == "gcls" else gcps_baseline_patterns(proj_cfg)
        tri = (
            PinholeTriangulator.from_sensor(cfg.sensor)
            if model == "pinhole"
            else reference_model_from_geometry(cfg.sensor)
        )
        view = scan_view(dev.camera, dev.projector, patterns, tri, bit_depth=cam_cfg.bit_depth)
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "cloud.ply", transform_points(T_W_C_reported, view.cloud.points_C[view.cloud.valid]))
    cv2.imwrite(str(out / "masks.png"), masks_image(view.cloud))
    summary = {
        "codec": codec,
        "n_images": len(patterns),
        "pattern_names": list(patterns.names),
        "triangulation": model,
        "geometry_source": "simulator: the cell config's nominal sensor geometry (no calibration applied)",
        "part": str(part_path) if part_path else None,
        "pose": {
            "T_W_C": T_W_C_reported.tolist(),
            "T_B_T": T_B_T.tolist(),
            "camera_xyz_rotvec": pose_to_xyz_rotvec(T_W_C_reported).tolist(),
        },
        "counts": view.reason_counts(),
        "mask_colours_bgr": {str(r.name).lower(): c for r, c in MASK_COLOURS},
        "timings_s": {**view.timings_s, "total": time.perf_counter() - t0},
        "cell_config": str(cell),
    }
    (out / "scan.json").write_text(json.dumps(summary, indent=2))
    return summary
