"""The body of ``cell scan``: build the simulated cell, move the robot, scan one view, write the results.

Until the calibration issue lands the triangulation uses the sensor geometry of the cell config, which is the
simulator's ground-truth geometry; scan.json says so (``geometry_source``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.calibration import active_hand_eye, believed_flange
from cell.config import CellConfig
from cell.contracts import CameraSettings, PixelFormat, ProjectorSource, TriggerMode
from cell.errors import ConfigError
from cell.geometry import invert, look_at, pose_to_xyz_rotvec, transform_points
from cell.planning.kinematics import UR5E
from cell.sensing.decode import Reason
from cell.sensing.patterns import gcls_patterns, gcps_patterns
from cell.sensing.scan import ViewScan, scan_view
from cell.sensing.triangulate import PinholeTriangulator, SensorCloud, reference_model_from_geometry

# masks.png colours (BGR) per reason, painted in this order so the last listed wins where several apply.
MASK_COLOURS: tuple[tuple[Reason, tuple[int, int, int]], ...] = (
    (Reason.NO_CODE, (60, 60, 60)),
    (Reason.DARK, (120, 0, 0)),  # dark blue: shadow / no projector light
    (Reason.LOW_CONTRAST, (0, 200, 255)),  # amber
    (Reason.INCONSISTENT, (255, 0, 255)),  # magenta
    (Reason.SATURATED, (0, 0, 255)),  # red: glare
)


def auto_pose(part_W: trimesh.Trimesh | None, standoff_mm: float) -> NDArray[np.float64]:
    """T_W_C looking straight down at the part's bounding-box centre (or the world origin) from the
    stand-off."""
    centre = part_W.bounds.mean(axis=0) if part_W is not None else np.zeros(3)
    return look_at(centre + (0.0, 0.0, standoff_mm), centre, up=(0.0, 1.0, 0.0))


def masks_image(cloud: SensorCloud) -> NDArray[np.uint8]:
    """BGR picture of the reasons: valid pixels in grey by contrast, the others in the
    :data:`MASK_COLOURS`."""
    grey = np.clip(np.nan_to_num(cloud.contrast) * 255, 0, 255).astype(np.uint8)
    img = np.repeat(grey[..., None], 3, axis=2)
    for reason, colour in MASK_COLOURS:
        img[(cloud.reasons & np.uint8(reason)) > 0] = colour
    return img


def write_ply(path: Path, points: NDArray) -> None:
    """Binary PLY of (N, 3) points (mm), through trimesh's exporter."""
    trimesh.PointCloud(np.asarray(points, dtype=np.float64)).export(str(path), file_type="ply")


def run_sim_scan(
    cfg: CellConfig,
    part_path: Path | None,
    T_W_C: NDArray[np.float64] | None,
    codec: str,
    model: str,
    out: Path,
    seed: int | None = None,
) -> dict[str, Any]:
    """Scan ``part_path`` (world mm) from camera pose ``T_W_C`` (None: :func:`auto_pose`); write cloud.ply and
    masks.png to ``out`` and return the scan.json content (timings, counts per reason, poses)."""
    from cell.devices import build_devices
    from cell.mesh import load_mesh

    if cfg.sensor.camera.driver != "sim":
        raise ConfigError(
            "cell scan triangulates with the simulator's known geometry until sensor "
            "calibration exists; use a cell whose drivers are all 'sim'",
            field="sensor.camera.driver",
        )
    part_W = load_mesh(part_path) if part_path is not None else None
    if T_W_C is None:
        T_W_C = auto_pose(part_W, cfg.sensor.standoff_mm)
    dev = build_devices(cfg, part_W=part_W, seed=seed)
    cam_cfg, proj_cfg = cfg.sensor.camera, cfg.sensor.projector
    for _, d in dev.items():
        d.connect()
    try:
        dev.projector.set_power(True)
        dev.projector.set_source(ProjectorSource.HDMI)
        dev.camera.configure(
            CameraSettings(
                cam_cfg.exposure_ms,
                cam_cfg.gain_db,
                PixelFormat(f"Mono{cam_cfg.bit_depth}"),
                TriggerMode.SOFTWARE,
            )
        )
        T_B_T = invert(cfg.robot.T_W_B.matrix()) @ T_W_C @ invert(cfg.sensor.T_T_C.matrix())
        # A joint move: a straight line from home may pass the base axis; IK picks the branch nearest to now.
        q = UR5E.ik_nearest(T_B_T, dev.robot.joints())
        dev.robot.move_joint(q, cfg.robot.max_joint_speed_rad_s, cfg.robot.max_joint_accel_rad_s2)
        # where the cell believes the camera is: the flange pose (calibrated kinematics when the cell has
        # them) through the active hand-eye (what a real cell knows; the simulator's true camera pose is not
        # the pipeline's to read)
        T_W_C_reported = cfg.robot.T_W_B.matrix() @ believed_flange(cfg, dev.robot) @ active_hand_eye(cfg)
        make = gcls_patterns if codec == "gcls" else gcps_patterns
        extra = {"n_shifts": 12} if codec == "gcls" else {"n_phase": 24}  # same number of images (38 at XGA)
        patterns = make(
            proj_cfg.width_px, proj_cfg.height_px, 12, **extra, n_gray=6 if proj_cfg.width_px >= 768 else None
        )
        tri = (
            PinholeTriangulator.from_sensor(cfg.sensor)
            if model == "pinhole"
            else reference_model_from_geometry(cfg.sensor)
        )
        view: ViewScan = scan_view(dev.camera, dev.projector, patterns, tri, bit_depth=cam_cfg.bit_depth)
    finally:
        for _, d in dev.items():
            d.close()
    out.mkdir(parents=True, exist_ok=True)
    pts_C = view.cloud.points_C[view.cloud.valid]
    pts_W = transform_points(T_W_C_reported, pts_C)
    write_ply(out / "cloud.ply", pts_W)
    cv2.imwrite(str(out / "masks.png"), masks_image(view.cloud))
    return {
        "codec": codec,
        "n_images": len(patterns),
        "pattern_names": list(patterns.names),
        "triangulation": model,
        "geometry_source": "simulator: the cell config's sensor geometry (no sensor calibration yet)",
        "part": str(part_path) if part_path else None,
        "pose": {
            "T_W_C": T_W_C_reported.tolist(),
            "T_B_T": T_B_T.tolist(),
            "camera_xyz_rotvec": pose_to_xyz_rotvec(T_W_C_reported).tolist(),
        },
        "counts": view.reason_counts(),
        "mask_colours_bgr": {r.name.lower(): c for r, c in MASK_COLOURS},
        "timings_s": dict(view.timings_s),
    }
