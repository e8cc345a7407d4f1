"""Offline routines on capture folders (:mod:`cell.calibration.capture_folder`): camera intrinsics, projector
(Moreno-Taubin), per-pixel sensor calibration and scans from images captured elsewhere. The same library
procedures as the online routines (:mod:`cell.calibration.intrinsics`, :mod:`cell.calibration.projector`,
:mod:`cell.calibration.sensor`); only the image source differs. Nothing here knows a simulator.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
from numpy.typing import NDArray

from cell.calibration.active import active_sensor_config, active_triangulator, calibration_source
from cell.calibration.capture_folder import MANIFEST, CaptureFolder, load_capture_folder
from cell.calibration.intrinsics import CharucoView, Intrinsics, calibrate_intrinsics
from cell.calibration.projector import ProjectorCalibration, calibrate_projector, corners_in_projector
from cell.calibration.sensor import SensorCalibration, SensorCalibrator, save_sensor_calibration
from cell.calibration.store import config_lines, load_calibration, load_metadata, save_calibration
from cell.config import CameraConfig, CellConfig, ProjectorConfig, config_fingerprint, load_cell_config
from cell.errors import CalibrationError, ConfigError
from cell.runs import RunFolder, write_json_atomic
from cell.sensing.scan import masks_image, write_ply
from cell.sensing.triangulate import SensorCloud, Triangulator
from cell.storage import new_folder


@dataclass
class OfflineProjector:
    """Projector calibration from a capture folder, with the camera intrinsics fitted on the same board views
    when none were given, and per pose how many corners had a projector position."""

    projector: ProjectorCalibration
    camera: Intrinsics | None
    decoded_corners: dict[str, int] = field(default_factory=dict)


def board_views(folder: CaptureFolder) -> list[CharucoView]:
    """The board corners of every pose (full-sensor px); CalibrationError naming the first pose without it."""
    board = folder.board()
    return [folder.find_board(pose, board) for pose in folder.poses]


def intrinsics_from_folder(folder: CaptureFolder, fix_k3: bool = True) -> Intrinsics:
    """Camera K and distortion from the board image of every pose."""
    return calibrate_intrinsics(board_views(folder), folder.board(), folder.camera_size, fix_k3)


def projector_from_folder(
    folder: CaptureFolder,
    K_cam: NDArray | None = None,
    dist_cam: NDArray | None = None,
    half_window: int = 15,
) -> OfflineProjector:
    """Moreno-Taubin projector calibration: per pose the board corners and the decoded projector coordinates
    (both directions), local homographies at the corners, then calibrateCamera for the projector and one
    bundle adjustment of camera and projector (cell.calibration.projector.calibrate_projector). Without
    ``K_cam`` the camera is calibrated on the same board views first."""
    if set(a.axis for a in folder.patterns.codes) != {"columns", "rows"}:
        raise ConfigError(
            "projector calibration needs both stripe directions: set code.direction to 'both'",
            path=str(folder.root / "capture.yaml"),
            field="code.direction",
        )
    board = folder.board()
    views, proj_px, valid, counts = [], [], [], {}
    for pose in folder.poses:
        view = folder.find_board(pose, board)  # before the stack: a missing board is the likelier mistake
        dec = folder.decode(pose)
        pp, ok = corners_in_projector(view, dec.axes["columns"].u, dec.axes["rows"].u, half_window)
        views.append(view)
        proj_px.append(pp)
        valid.append(ok)
        counts[pose.name] = int(ok.sum())
    camera = None
    if K_cam is None:
        camera = calibrate_intrinsics(views, board, folder.camera_size)
        K_cam, dist_cam = camera.K, camera.dist
    elif dist_cam is None:
        raise ConfigError("projector calibration: camera intrinsics K_cam given without their distortion")
    res = calibrate_projector(
        views, proj_px, valid, board, K_cam, dist_cam, folder.camera_size, folder.projector_size
    )
    return OfflineProjector(res, camera, counts)


def sensor_from_folder(
    folder: CaptureFolder,
    camera: CameraConfig,
    projector: ProjectorConfig,
    reference_depth_mm: float,
    n_points: int = 65536,
    eval_height_mm: float = 30.0,
    K: NDArray | None = None,
    dist: NDArray | None = None,
) -> SensorCalibration:
    """Per-pixel calibration (dissertation 5.1.1) from poses of the flat board at the manifest's
    ``height_mm`` (the first at 0: the reference plane), decoded in both directions."""
    _same_devices(folder, camera, projector)
    missing = [p.name for p in folder.poses if p.height_mm is None]
    if missing:
        raise ConfigError(
            f"sensor calibration needs height_mm for every pose; missing for {', '.join(missing)}",
            path=str(folder.root / "capture.yaml"),
            field="poses",
        )
    cal = SensorCalibrator(
        camera, projector, reference_depth_mm, n_points, K, dist, eval_height_mm=eval_height_mm
    )
    steps = [(p.height_mm, p) for p in folder.poses if p.height_mm is not None]  # all of them (checked)
    for height_mm, pose in sorted(steps, key=lambda s: s[0]):
        try:
            cal.add_step(height_mm, folder.decode(pose))
        except CalibrationError as exc:
            raise CalibrationError(f"pose '{pose.name}' (height {height_mm} mm): {exc}") from exc
    return cal.finish()


def scan_folder(
    folder: CaptureFolder, triangulator: Triangulator, camera: CameraConfig, projector: ProjectorConfig
) -> dict[str, SensorCloud]:
    """One cloud (camera frame, mm) per pose, measured with the cell's ``triangulator``."""
    _same_devices(folder, camera, projector)
    return {
        pose.name: triangulator.triangulate(folder.decode(pose, stack)) for pose, stack in folder.iter_poses()
    }


def _same_devices(folder: CaptureFolder, camera: CameraConfig, projector: ProjectorConfig) -> None:
    """The images must come from a camera and projector of the cell's resolutions."""
    for what, spec, dev in (
        ("camera", folder.manifest.camera, camera),
        ("projector", folder.manifest.projector, projector),
    ):
        if (spec.width_px, spec.height_px) != (dev.width_px, dev.height_px):
            raise ConfigError(
                f"the capture's {what} is {spec.width_px}x{spec.height_px}, the cell's '{dev.name}' is "
                f"{dev.width_px}x{dev.height_px}: images from another device",
                path=str(folder.root / "capture.yaml"),
                field=f"{what}.width_px",
            )


def projector_figures(res: OfflineProjector) -> dict[str, Any]:
    """The figures the command prints and stores."""
    p = res.projector
    figs: dict[str, Any] = {
        "views": p.views,
        "corners": p.corners,
        "rms_px": p.rms_px,
        "stereo_rms_px": p.stereo_rms_px,
        "K": p.K.tolist(),
        "dist": p.dist.tolist(),
        "T_C_P": p.T_C_P.tolist(),
        "decoded_corners": res.decoded_corners,
    }
    if res.camera is not None:
        figs["camera"] = {
            "rms_px": res.camera.rms_px,
            "K": res.camera.K.tolist(),
            "dist": res.camera.dist.tolist(),
        }
    return figs


def _device(spec: Any) -> dict[str, Any]:
    dev: dict[str, Any] = {"resolution": [spec.width_px, spec.height_px]}
    if spec.serial is not None:  # recorded only when the manifest names it (active.py checks it then)
        dev["serial"] = spec.serial
    return dev


def save_offline_intrinsics(
    res: Intrinsics, folder: CaptureFolder, path: Path, force: bool = False, made_for: str | None = None
) -> Path:
    """The camera_intrinsics file (kind and keys as ``cell calibrate intrinsics``) of a capture folder."""
    figs = {
        "views": len(res.view_rms_px),
        "rms_px": res.rms_px,
        "max_view_rms_px": float(res.view_rms_px.max()),
        "K": res.K.tolist(),
        "dist": res.dist.tolist(),
    }
    meta = {
        "camera": _device(folder.manifest.camera),
        "source": str(folder.root.resolve()),
        "figures": figs,
        "quality": {"rms_px": res.rms_px},
    }
    return save_calibration(
        path,
        "camera_intrinsics",
        {"K": res.K, "dist": res.dist},
        meta,
        "quality.rms_px",
        force,
        made_for=made_for,
    )


def save_offline_projector(
    res: OfflineProjector, folder: CaptureFolder, path: Path, force: bool = False, made_for: str | None = None
) -> Path:
    """The projector file (same kind and keys as ``cell calibrate projector``) of a capture folder."""
    p = res.projector
    meta = {
        "projector": _device(folder.manifest.projector),
        "camera": _device(folder.manifest.camera),
        "source": str(folder.root.resolve()),
        "figures": projector_figures(res),
        "quality": {"rms_px": p.stereo_rms_px},
    }
    arrays = {"K": p.K, "dist": p.dist, "T_C_P": p.T_C_P, "camera_K": p.K_cam, "camera_dist": p.dist_cam}
    return save_calibration(path, "projector", arrays, meta, "quality.rms_px", force, made_for=made_for)


def run_offline(
    routine: str,
    folder: CaptureFolder,
    out_dir: Path,
    cell: Path,
    intrinsics: Path | None = None,
    force: bool = False,
    points: int = 65536,
) -> tuple[str, Path, dict[str, Any]]:
    """Body of ``cell calibrate intrinsics|projector|sensor --from SOURCE``: calibrate from the capture
    folder (:func:`load_capture_folder`), write the calibration file into ``out_dir``; returns (kind, file,
    figures).
    ``intrinsics``: a camera intrinsics file for the projector routine (default: calibrate the camera on
    the same board views).
    ``cell``: the cell config the sensor routine calibrates (its camera, projector, stand-off, lens);
    ``points``: its number of encoded points."""
    cfg = load_cell_config(cell)
    made_for = config_fingerprint(cfg)  # the cell the files are made for
    if routine == "intrinsics":
        res = intrinsics_from_folder(folder)
        path = save_offline_intrinsics(res, folder, out_dir / "intrinsics", force, made_for)
        return "camera_intrinsics", path, load_metadata(path)["figures"]
    if routine == "projector":
        K = dist = None
        if intrinsics is not None:
            meta, arrays = load_calibration(intrinsics, "camera_intrinsics")
            if list(meta["camera"]["resolution"]) != list(folder.camera_size):
                raise ConfigError(
                    f"intrinsics for a {meta['camera']['resolution']} camera, the capture's is "
                    f"{folder.camera_size[0]}x{folder.camera_size[1]}",
                    path=str(intrinsics),
                    field="camera.resolution",
                )
            K, dist = arrays["K"], arrays["dist"]
        pres = projector_from_folder(folder, K, dist)
        return (
            "projector",
            save_offline_projector(pres, folder, out_dir / "projector", force, made_for),
            projector_figures(pres),
        )
    if routine == "sensor":
        cam = active_sensor_config(cfg).camera
        sres = sensor_from_folder(
            folder,
            cam,
            cfg.sensor.projector,
            cfg.sensor.standoff_mm,
            points,
            eval_height_mm=cfg.sensor.depth_of_field_mm / 2,
        )
        path = save_sensor_calibration(
            sres, out_dir / "sensor", cam, cfg.sensor.projector, force=force, made_for=made_for
        )
        return "sensor_per_pixel", path, sres.figures
    raise ConfigError(f"no offline routine '{routine}'; use intrinsics, projector or sensor")


def calibrate_from_folder(
    routine: str, source: Path, out: Path, cell: Path, **options: Any
) -> dict[str, Any]:
    """``cell calibrate intrinsics|projector|sensor --from SOURCE``: :func:`run_offline` in the run folder
    ``out`` (made, or reopened to calibrate again), with the cell config and the capture folder's manifest
    copied into its inputs. Writes and returns ``calibration.json``: kind, file, source, the figures
    (``summary``) and the lines for the cell config."""
    folder = load_capture_folder(source)  # checked before the run folder is made
    if (out / "journal.jsonl").exists():
        run = RunFolder.open(out)
        run.copy_input(cell, "cell.yaml")
        run.copy_input(source / MANIFEST, MANIFEST)
    else:
        with new_folder(out):  # a full disk or read-only folder: refused, nothing left behind
            run = RunFolder.create(out.parent, "calibration", name=out.name)
            run.copy_input(cell, "cell.yaml")
            run.copy_input(source / MANIFEST, MANIFEST)
    kind, path, figs = run_offline(routine, folder, run.path, cell, **options)
    report: dict[str, Any] = {"kind": kind, "file": str(path), "source": str(source), "summary": figs}
    report["cell_config_lines"] = config_lines(kind, path)
    write_json_atomic(run.path / "calibration.json", report)
    run.log("done", report="calibration.json")
    return report


def write_folder_scan(cfg: CellConfig, source: Path, out: Path) -> dict[str, Any]:
    """Body of ``cell scan --from SOURCE``: every pose measured with the cell's active calibration; writes
    ``<pose>.ply`` (camera frame, mm), ``<pose>_masks.png`` and ``scan.json`` into ``out``; returns the
    scan.json content."""
    folder = load_capture_folder(source)
    sensor = active_sensor_config(cfg)
    clouds = scan_folder(folder, active_triangulator(cfg), sensor.camera, sensor.projector)
    out.mkdir(parents=True, exist_ok=True)
    poses = {}
    for name, cloud in clouds.items():
        write_ply(out / f"{name}.ply", cloud.points_C[cloud.valid])
        cv2.imwrite(str(out / f"{name}_masks.png"), masks_image(cloud))
        poses[name] = {"points": int(cloud.valid.sum()), "frame": "camera {C}, mm"}
    summary = {
        "source": str(Path(source).resolve()),
        "geometry_source": calibration_source(cfg),
        "poses": poses,
    }
    (out / "scan.json").write_text(json.dumps(summary, indent=2))
    return summary
