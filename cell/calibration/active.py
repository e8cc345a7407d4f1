"""The calibration the inspection job measures with: the files named in the cell config's ``calibration:``
section, or the config's nominal geometry when none is set."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.calibration.gamma import apply_lut
from cell.calibration.kinematics import KinematicErrors, camera_pose_spread
from cell.calibration.sensor import load_sensor_model
from cell.calibration.store import load_calibration, load_metadata
from cell.config import CellConfig, Distortion, PoseConfig, SensorConfig
from cell.contracts import Robot
from cell.errors import ConfigError
from cell.geometry import Pose
from cell.sensing.error_model import one_pixel_error
from cell.sensing.patterns import PatternSet, measuring_patterns
from cell.sensing.triangulate import PinholeTriangulator, Triangulator

NO_CALIBRATION = "config geometry (no calibration)"


def _rigid(T: NDArray, path: Path, name: str) -> Pose:
    T = np.asarray(T, dtype=np.float64)
    if (
        T.shape != (4, 4)
        or not np.allclose(T[3], (0, 0, 0, 1))
        or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    ):
        raise ConfigError(f"calibration file holds no rigid 4x4 {name}", path=str(path), field=name)
    return T


def _pose_config(T: Pose) -> PoseConfig:
    """The config's xyz + fixed-axis rpy (degrees) of a 4x4 pose (inverse of PoseConfig.matrix)."""
    rpy = np.degrees(Rotation.from_matrix(T[:3, :3]).as_euler("xyz"))
    return PoseConfig(xyz_mm=tuple(T[:3, 3].tolist()), rpy_deg=tuple(rpy.tolist()))


def _check_device(meta: dict, key: str, path: Path, serial: str, size: tuple[int, int]) -> None:
    """A calibration belongs to one device: same resolution and, when recorded, the same serial."""
    dev = meta.get(key, {})
    if list(dev.get("resolution", size)) != list(size):
        raise ConfigError(
            f"calibration is for a {dev['resolution']} {key}, the cell's is {size[0]}x{size[1]}: "
            "resolution mismatch; recalibrate or remove the entry",
            path=str(path),
            field=f"{key}.resolution",
        )
    if dev.get("serial", serial) != serial:
        raise ConfigError(
            f"calibration was made for {key} serial '{dev['serial']}', the cell's {key} is '{serial}'; "
            "recalibrate or remove the entry",
            path=str(path),
            field=f"{key}.serial",
        )


def _pinhole_update(K: NDArray) -> dict[str, float]:
    (fx, _, cx), (_, fy, cy) = np.asarray(K, dtype=np.float64)[:2].tolist()
    return {"fx_px": fx, "fy_px": fy, "cx_px": cx, "cy_px": cy}


def _lens(coefficients: NDArray) -> Distortion:
    """OpenCV distortion coefficients (any length) as the config's five (k1, k2, p1, p2, k3)."""
    dist = np.zeros(5)
    dist[: min(5, np.size(coefficients))] = np.ravel(coefficients)[:5]
    return Distortion(**dict(zip(Distortion.model_fields, dist.tolist(), strict=True)))


def active_sensor_config(cfg: CellConfig) -> SensorConfig:
    """``cfg.sensor`` with the calibrated values put in (a copy; ``cfg`` is not changed):

    * ``calibration.intrinsics`` (cell calibrate intrinsics): camera fx, fy, cx, cy and distortion;
    * ``calibration.projector`` (cell calibrate projector): projector fx, fy, cx, cy, distortion and T_C_P,
      and the camera lens refined with them (``camera_K``, ``camera_dist``) when the file holds it: the
      transform is consistent only with that camera (cell.calibration.projector), so it replaces the
      intrinsics file's;
    * ``calibration.hand_eye`` (cell calibrate handeye): T_T_C.

    Each file must be of the right kind and made for the configured device (resolution, serial)."""
    s = cfg.sensor.model_copy(deep=True)
    cal = cfg.calibration
    cam, proj = s.camera, s.projector
    if cal.intrinsics is not None:
        meta, a = load_calibration(cal.intrinsics, "camera_intrinsics")
        _check_device(meta, "camera", cal.intrinsics, cam.serial, (cam.width_px, cam.height_px))
        cam = cam.model_copy(update={**_pinhole_update(a["K"]), "distortion": _lens(a["dist"])})
    if cal.projector is not None:
        meta, a = load_calibration(cal.projector, "projector")
        _check_device(meta, "projector", cal.projector, proj.serial, (proj.width_px, proj.height_px))
        T_C_P = _rigid(a["T_C_P"], cal.projector, "T_C_P")
        update_p = {**_pinhole_update(a["K"]), "T_C_P": _pose_config(T_C_P)}
        if "dist" in a:
            update_p["distortion"] = _lens(a["dist"])
        proj = proj.model_copy(update=update_p)
        if "camera_K" in a:  # the camera lens the pair was adjusted with
            _check_device(meta, "camera", cal.projector, cam.serial, (cam.width_px, cam.height_px))
            update_c = {**_pinhole_update(a["camera_K"]), "distortion": _lens(a["camera_dist"])}
            cam = cam.model_copy(update=update_c)
    update: dict = {"camera": cam, "projector": proj}
    if cal.hand_eye is not None:
        update["T_T_C"] = _pose_config(active_hand_eye(cfg))
    return s.model_copy(update=update)


def active_triangulator(cfg: CellConfig) -> Triangulator:
    """The calibrated per-pixel reference-plane model when ``cfg.calibration.sensor`` is set (checked against
    the camera's resolution), else the pinhole model from :func:`active_sensor_config` (the calibrated camera
    and projector when their files are set, else the config's geometry)."""
    if cfg.calibration.sensor is not None:
        return load_sensor_model(cfg.calibration.sensor, cfg.sensor.camera)
    return PinholeTriangulator.from_sensor(active_sensor_config(cfg))


def active_hand_eye(cfg: CellConfig) -> Pose:
    """``T_T_C`` (4x4, mm): the hand-eye calibration file when ``cfg.calibration.hand_eye`` is set, else the
    configured ``sensor.T_T_C`` (the mounting drawing)."""
    if cfg.calibration.hand_eye is None:
        return cfg.sensor.T_T_C.matrix()
    _, arrays = load_calibration(cfg.calibration.hand_eye, "hand_eye")
    return _rigid(arrays["T_T_C"], cfg.calibration.hand_eye, "T_T_C")


def active_kinematics(cfg: CellConfig) -> KinematicErrors | None:
    """The robot's calibrated kinematic errors (``calibration.kinematics``, cell calibrate kinematics), or
    None: the robot's own reported flange pose is used."""
    if cfg.calibration.kinematics is None:
        return None
    _, a = load_calibration(cfg.calibration.kinematics, "robot_kinematics")
    for key in ("dd", "da", "dq"):
        if np.shape(a[key]) != (6,):
            raise ConfigError(
                f"{cfg.calibration.kinematics}: '{key}' must hold 6 values, it holds {np.shape(a[key])}; run "
                "`cell calibrate kinematics` again",
                field="calibration.kinematics",
            )
    return KinematicErrors(*(np.asarray(a[k], dtype=np.float64) for k in ("dd", "da", "dq")))


def view_pose_prior(cfg: CellConfig, joints: list[NDArray[np.float64]] | None) -> tuple[NDArray, str]:
    """Per view, the 1-sigma error (per axis) of its camera pose relative to the other views: column 0 in mm
    (at the stand-off), column 1 in rad; the multi-view refinement's prior. With a kinematic calibration that
    holds its covariance: the larger of what the fit leaves at the view's reported ``joints`` (rad) and the
    robot config's ``calibrated_view_pose_sigma_mm/deg``. The fit's covariance alone is overconfident: it
    comes from the scatter of its residuals, while the bias that the calibrated (not exact) lenses put into
    its board poses moves the camera further (measured in the honest simulated world: <= 0.003 deg predicted,
    0.010-0.021 deg found between the demo's views). Without one, the config's ``view_pose_sigma_mm/deg``.
    Also says which."""
    robot = cfg.robot
    n = 0 if joints is None else len(joints)
    if cfg.calibration.kinematics is not None and joints is not None and n >= 2:
        _, a = load_calibration(cfg.calibration.kinematics, "robot_kinematics")
        if "x" in a and "covariance" in a:
            spread = camera_pose_spread(
                np.asarray(a["x"], dtype=np.float64),
                np.asarray(a["covariance"], dtype=np.float64),
                joints,
                cfg.sensor.standoff_mm,
            )
            floor = [robot.calibrated_view_pose_sigma_mm, np.deg2rad(robot.calibrated_view_pose_sigma_deg)]
            return np.maximum(spread, floor), (
                f"kinematic calibration {cfg.calibration.kinematics}, at least "
                "robot.calibrated_view_pose_sigma_mm/deg"
            )
    sigma = np.tile([robot.view_pose_sigma_mm, np.deg2rad(robot.view_pose_sigma_deg)], (n, 1))
    return sigma, "robot.view_pose_sigma_mm/deg"


def believed_flange(cfg: CellConfig, robot: Robot) -> Pose:
    """``T_B_T`` where the flange is: the calibrated kinematics at the robot's reported joints when the cell
    has them, else the pose the robot reports (its nominal kinematics)."""
    errors = active_kinematics(cfg)
    return robot.tool_pose() if errors is None else errors.flange(robot.joints())


def active_gamma_lut(cfg: CellConfig) -> NDArray[np.uint8] | None:
    """The projector's linearising LUT (256 grey levels) of ``calibration.gamma`` (cell calibrate gamma), or
    None without one; ConfigError when the file is not a 256-entry LUT."""
    if cfg.calibration.gamma is None:
        return None
    _, arrays = load_calibration(cfg.calibration.gamma, "projector_gamma")
    lut = np.asarray(arrays["lut"])
    if lut.shape != (256,):
        raise ConfigError(
            f"{cfg.calibration.gamma}: 'lut' must hold 256 grey levels, it holds {lut.shape}; run "
            "`cell calibrate gamma` again",
            field="calibration.gamma",
        )
    return lut.astype(np.uint8)


def active_measuring_patterns(cfg: CellConfig) -> PatternSet:
    """The measuring code (GCLS) as this cell projects it: through the projector's linearising LUT when
    ``calibration.gamma`` names one. Every measurement (inspection, verification, validation, the hand-eye's
    gauge scans, ``cell scan``) projects this set: the line-shift edges are ramped in grey
    (:data:`cell.sensing.patterns.MEASURING_EDGE_PX`), which a non-linear projector would bend."""
    patterns = measuring_patterns(cfg.sensor.projector)
    lut = active_gamma_lut(cfg)
    return patterns if lut is None else apply_lut(patterns, lut)


def calibration_source(cfg: CellConfig) -> str:
    """One line saying what the measurements rest on, for reports: the active calibration files (name and
    creation date) and what still comes from the config's nominal geometry."""
    cal = cfg.calibration
    parts = []
    for field in ("sensor", "intrinsics", "projector", "hand_eye", "kinematics", "gamma"):
        path = getattr(cal, field)
        if path is not None:
            created = load_metadata(path).get("created_utc", "undated")
            parts.append(f"{field}: {Path(path).name} ({created})")
    if not parts:
        return NO_CALIBRATION
    if cal.sensor is None:
        refined = cal.projector is not None and "camera_K" in load_calibration(cal.projector, "projector")[1]
        if refined:
            parts.append("camera lens: as refined with the projector")
        missing = [f for f in ("intrinsics", "projector") if getattr(cal, f) is None]
        if refined and "intrinsics" in missing:
            missing.remove("intrinsics")
        if missing:
            parts.append(f"{' and '.join(missing)}: config geometry")
    if cal.hand_eye is None:
        parts.append("hand_eye: config sensor.T_T_C")
    return "; ".join(parts)


# Of the projector calibration's stereo reprojection rms, the share that measurements inherit as a systematic
# correspondence error: the rest is the board corners' random detection noise, which the fit averages out (the
# residual cannot tell them apart). Calibrated in the honest simulated world (docs/uncertainty.md: with the
# whole rms the points' decode u exceeded their error by a third).
STEREO_RESIDUAL_SHARE = 0.5


def calibration_residual_px(cfg: CellConfig) -> tuple[float, str]:
    """The active calibration's own residual as a correspondence error (camera px, 1 sigma) and where it comes
    from, for the per-point uncertainty (cell.analysis.uncertainty): the per-pixel model's median eq 2.7
    residual (mm) over the one-pixel height error of eq 2.5 at the reference plane, else the projector
    calibration's stereo reprojection rms times :data:`STEREO_RESIDUAL_SHARE`, else 0 (the config's nominal
    geometry: nothing measured it)."""
    cal = cfg.calibration
    if cal.sensor is not None:
        residual = load_metadata(cal.sensor).get("quality", {}).get("median_residual_mm")
        if residual is not None:
            s = cfg.sensor
            baseline = float(np.linalg.norm(s.projector.T_C_P.matrix()[:2, 3]))
            per_px = float(one_pixel_error(s.standoff_mm / s.camera.fx_px, s.standoff_mm, baseline, 0.0))
            return float(residual) / per_px, f"per-pixel model {Path(cal.sensor).name}: eq 2.7 residual"
    if cal.projector is not None:
        rms = load_metadata(cal.projector).get("figures", {}).get("stereo_rms_px")
        if rms is not None:
            return STEREO_RESIDUAL_SHARE * float(rms), (
                f"projector calibration {Path(cal.projector).name}: {STEREO_RESIDUAL_SHARE:g} x its stereo "
                "reprojection rms"
            )
    return 0.0, NO_CALIBRATION


def pose_uncertainty_prior(cfg: CellConfig, refinement_prior: dict[str, Any]) -> dict[str, Any]:
    """The views' pose prior the per-point uncertainty assumes (cell.analysis.uncertainty): with a kinematic
    calibration the robot config's ``pose_uncertainty_mm/deg`` for every view (the refinement's prior floor
    errs on the large side on purpose), else the prior the refinement ran under (``refinement_prior``, its
    record: ``prior_sigma_mm``, ``prior_sigma_deg`` per view)."""
    n = len(refinement_prior.get("prior_sigma_mm", []))
    if cfg.calibration.kinematics is None or not n:
        return refinement_prior
    robot = cfg.robot
    return {
        "prior": "robot.pose_uncertainty_mm/deg (with the kinematic calibration)",
        "prior_sigma_mm": [robot.pose_uncertainty_mm] * n,
        "prior_sigma_deg": [robot.pose_uncertainty_deg] * n,
    }
