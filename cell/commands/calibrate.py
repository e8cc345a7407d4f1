"""``cell calibrate sensor|intrinsics|projector|gamma|handeye|validate``: the technician's calibration
routines
on the configured cell. Each writes a run folder ``--out`` (journal + ``calibration.json`` or
``validation.json``) and prints the lines to put into the cell config; it never edits the config itself. Only
simulated cells are supported so far: the reference-board stage, the ChArUco board and the gauge come from the
simulator."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cell.config import DEFAULT_CELL, CellConfig, load_cell_config
from cell.errors import ConfigError
from cell.runs import RunFolder, write_json_atomic

calibrate_app = typer.Typer(
    help="Calibration routines: per-pixel sensor, camera intrinsics, projector, projector "
    "gamma, hand-eye, validation.",
    no_args_is_help=True,
)
CellOpt = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML")
OutOpt = typer.Option(..., "--out", help="run folder to write")
GAUGE = DEFAULT_CELL.parent.parent / "parts" / "gauge.stl"
FromOpt = typer.Option(
    None, "--from", help="capture folder of images taken elsewhere (docs/capture-folders.md)"
)


def _sim_cell(path: Path) -> CellConfig:
    cfg = load_cell_config(path)
    if cfg.sensor.camera.driver != "sim" or cfg.sensor.projector.driver != "sim":
        raise ConfigError(
            "calibration routines drive the simulated reference stage and gauge; use a cell whose "
            "camera and projector drivers are 'sim'",
            path=str(path),
            field="sensor.camera.driver",
        )
    return cfg


def _folder(out: Path, cell: Path) -> RunFolder:
    run = (
        RunFolder.open(out)
        if (out / "journal.jsonl").exists()
        else RunFolder.create(out.parent, "calibration", name=out.name)
    )
    run.copy_input(cell, "cell.yaml")
    return run


def _finish(run: RunFolder, name: str, report: dict[str, Any], config_lines: str | None = None) -> None:
    if config_lines:
        report["cell_config_lines"] = config_lines
    write_json_atomic(run.path / name, report)
    run.log("done", report=name)
    typer.echo(json.dumps(report.get("summary", report), indent=2, default=str))
    if config_lines:
        typer.echo(
            "\nTo use it, put this into the cell config (paths may be made relative to the cell file):\n"
            + config_lines
        )


def _calibration_lines(field: str, path: Path) -> str:
    return f"calibration:\n  {field}: {Path(path).resolve()}"


def _offline(routine: str, source: Path, out: Path, cell: Path, **kw: Any) -> None:
    """``--from SOURCE``: the routine on a capture folder (cell.calibration.offline)."""
    from cell.calibration.capture_folder import MANIFEST, load_capture_folder
    from cell.calibration.offline import run_offline

    folder = load_capture_folder(source)  # checked before the run folder is made
    run = _folder(out, cell)
    run.copy_input(source / MANIFEST, MANIFEST)
    kind, path, figs = run_offline(routine, folder, run.path, cell, **kw)
    field = {"camera_intrinsics": "intrinsics", "sensor_per_pixel": "sensor"}.get(kind, kind)
    report = {"kind": kind, "file": str(path), "source": str(source), "summary": figs}
    _finish(run, "calibration.json", report, _calibration_lines(field, path))


@calibrate_app.command("sensor")
def sensor_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    steps: int = typer.Option(30, min=3),
    step_mm: float = typer.Option(1.0, min=0.01),
    points: int = typer.Option(65536, min=16),
    force: bool = typer.Option(False, "--force", help="replace a better existing calibration"),
    seed: int = 1,
    source: Path | None = FromOpt,
) -> None:
    """Per-pixel calibration: step the reference board STEPS x STEP_MM toward the sensor (dissertation
    5.1.1)."""
    if source is not None:
        return _offline("sensor", source, out, cell, force=force, points=points)
    from cell.calibration.active import active_sensor_config
    from cell.calibration.sensor import SensorCalibrator, save_sensor_calibration
    from cell.sensing.decode import decode
    from cell.sensing.patterns import gcls_patterns
    from fakes.sim.board import SteppedReferenceBoard

    cfg = _sim_cell(cell)
    run = _folder(out, cell)
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    rig = SteppedReferenceBoard(cfg.sensor, cfg.sim)
    ps = gcls_patterns(
        proj.width_px, proj.height_px, 12, 6, "both", n_gray=6 if proj.width_px >= 768 else None
    )
    cam = active_sensor_config(cfg).camera  # the calibrated lens when calibration.intrinsics is set
    cal = SensorCalibrator(
        cam, proj, cfg.sensor.standoff_mm, n_points=points, eval_height_mm=cfg.sensor.depth_of_field_mm / 2
    )
    rng = np.random.default_rng(seed)
    for k in range(steps + 1):
        found = cal.add_step(k * step_mm, decode(rig.capture(k * step_mm, ps.frames, rng), ps, cam.bit_depth))
        run.log("step", index=k, height_mm=k * step_mm, encoded_points=found)
        typer.echo(f"step {k}/{steps} at {k * step_mm:.2f} mm: {found} encoded points", err=True)
    res = cal.finish()
    path = save_sensor_calibration(res, run.path / "sensor", cam, proj, force=force)
    _finish(
        run,
        "calibration.json",
        {"kind": "sensor_per_pixel", "file": str(path), "summary": res.figures},
        _calibration_lines("sensor", path),
    )


def _board_scene(cfg: CellConfig, squares: tuple[int, int], square_mm: float, marker_mm: float):  # noqa: ANN202
    """The simulated ChArUco board, its texture and a renderer (the board is drawn in front of everything)."""
    import trimesh

    from fakes.sim.board import board_texture, charuco_board
    from fakes.sim.render import SceneRenderer
    from fakes.sim.scene import Scene

    board = charuco_board(squares, square_mm, marker_mm)
    tex, ppm = board_texture(board)
    renderer = SceneRenderer(cfg.sensor, cfg.sim, Scene.from_meshes(trimesh.creation.box((1, 1, 1)), cfg.sim))
    return board, tex, ppm, renderer


@calibrate_app.command("intrinsics")
def intrinsics_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    views: int = typer.Option(12, min=1),
    force: bool = typer.Option(False, "--force", help="replace a better existing calibration"),
    seed: int = 1,
    source: Path | None = FromOpt,
) -> None:
    """Camera K and distortion from VIEWS images of a ChArUco board (OpenCV CharucoDetector,
    calibrateCamera)."""
    if source is not None:
        return _offline("intrinsics", source, out, cell, force=force)
    from cell.calibration.intrinsics import calibrate_intrinsics, detect_charuco
    from cell.calibration.store import save_calibration
    from fakes.sim.board import board_poses, render_textured_board

    cfg = _sim_cell(cell)
    run = _folder(out, cell)
    cam = cfg.sensor.camera
    board, tex, ppm, renderer = _board_scene(cfg, (11, 8), 15.0, 11.0)
    rng = np.random.default_rng(seed)
    found = []
    for i, T in enumerate(board_poses(board, cfg.sensor.standoff_mm, views, rng)):
        v = detect_charuco(render_textured_board(renderer, T, tex, ppm, rng), board)
        run.log("view", index=i, corners=0 if v is None else len(v.ids))
        found.append(v)
    res = calibrate_intrinsics(found, board, (cam.width_px, cam.height_px))
    figs = {
        "views": len(res.view_rms_px),
        "rms_px": res.rms_px,
        "max_view_rms_px": float(res.view_rms_px.max()),
        "K": res.K.tolist(),
        "dist": res.dist.tolist(),
    }
    path = save_calibration(
        run.path / "intrinsics",
        "camera_intrinsics",
        {"K": res.K, "dist": res.dist},
        {
            "camera": {"serial": cam.serial, "resolution": [cam.width_px, cam.height_px]},
            "figures": figs,
            "quality": {"rms_px": res.rms_px},
        },
        "quality.rms_px",
        force,
    )
    _finish(
        run,
        "calibration.json",
        {"kind": "camera_intrinsics", "file": str(path), "summary": figs},
        _calibration_lines("intrinsics", path),
    )


@calibrate_app.command("projector")
def projector_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    views: int = typer.Option(6, min=1),
    intrinsics: Path | None = typer.Option(
        None,
        help="camera intrinsics file (cell calibrate intrinsics); default: the cell's active camera "
        "(calibration.intrinsics, else the configured lens)",
    ),
    force: bool = typer.Option(False, "--force", help="replace a better existing calibration"),
    seed: int = 1,
    source: Path | None = FromOpt,
) -> None:
    """Projector K and T_C_P (Moreno-Taubin local homographies at the ChArUco corners, stereoCalibrate)."""
    if source is not None:
        return _offline("projector", source, out, cell, intrinsics=intrinsics, force=force)
    from cell.calibration.active import active_sensor_config
    from cell.calibration.intrinsics import detect_charuco
    from cell.calibration.projector import calibrate_projector, corners_in_projector
    from cell.calibration.store import load_calibration, save_calibration
    from cell.sensing.decode import decode
    from cell.sensing.patterns import gcps_patterns
    from fakes.sim.board import board_poses, render_textured_board, render_textured_board_stack

    cfg = _sim_cell(cell)
    run = _folder(out, cell)
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    active_cam = active_sensor_config(cfg).camera
    K, dist = active_cam.K(), active_cam.distortion.as_array()
    if intrinsics is not None:
        _, arrays = load_calibration(intrinsics, "camera_intrinsics")
        K, dist = arrays["K"], arrays["dist"]
    board, tex, ppm, renderer = _board_scene(cfg, (11, 8), 15.0, 11.0)
    ps = gcps_patterns(proj.width_px, proj.height_px, 16, 4, "both")
    rng = np.random.default_rng(seed)
    found, proj_px, valid = [], [], []
    for i, T in enumerate(board_poses(board, cfg.sensor.standoff_mm, views, rng)):
        v = detect_charuco(render_textured_board(renderer, T, tex, ppm, rng), board)
        if v is None:
            run.log("view_skipped", index=i, reason="board not found")
            continue
        dec = decode(render_textured_board_stack(renderer, T, tex, ppm, ps.frames, rng), ps, cam.bit_depth)
        pp, ok = corners_in_projector(v, dec.axes["columns"].u, dec.axes["rows"].u)
        run.log("view", index=i, corners=len(v.ids), decoded_corners=int(ok.sum()))
        found.append(v)
        proj_px.append(pp)
        valid.append(ok)
    res = calibrate_projector(
        found, proj_px, valid, board, K, dist, (cam.width_px, cam.height_px), (proj.width_px, proj.height_px)
    )
    figs = {
        "views": res.views,
        "corners": res.corners,
        "rms_px": res.rms_px,
        "stereo_rms_px": res.stereo_rms_px,
        "K": res.K.tolist(),
        "dist": res.dist.tolist(),
        "T_C_P": res.T_C_P.tolist(),
    }
    path = save_calibration(
        run.path / "projector",
        "projector",
        {"K": res.K, "dist": res.dist, "T_C_P": res.T_C_P},
        {
            "projector": {"serial": proj.serial, "resolution": [proj.width_px, proj.height_px]},
            "figures": figs,
            "quality": {"rms_px": res.stereo_rms_px},
        },
        "quality.rms_px",
        force,
    )
    _finish(
        run,
        "calibration.json",
        {"kind": "projector", "file": str(path), "summary": figs},
        _calibration_lines("projector", path),
    )


@calibrate_app.command("gamma")
def gamma_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    levels: int = typer.Option(17, min=3),
    force: bool = typer.Option(False, "--force"),
    seed: int = 1,
) -> None:
    """Projector response: uniform grey levels on the white board; writes the linearising LUT."""
    from cell.calibration.gamma import gamma_figures, grey_levels, linearising_lut, measure_response
    from cell.calibration.store import save_calibration
    from fakes.sim.board import SteppedReferenceBoard

    cfg = _sim_cell(cell)
    run = _folder(out, cell)
    proj = cfg.sensor.projector
    lv = grey_levels(levels)
    frames = np.stack([np.full((proj.height_px, proj.width_px), g, np.uint8) for g in lv])
    response = measure_response(
        SteppedReferenceBoard(cfg.sensor, cfg.sim).capture(0.0, frames, np.random.default_rng(seed)), lv
    )
    lut = linearising_lut(lv, response)
    figs = gamma_figures(lv, response)
    path = save_calibration(
        run.path / "gamma",
        "projector_gamma",
        {"lut": lut},
        {"projector": {"name": proj.name}, "figures": figs},
        force=force,
    )
    _finish(
        run,
        "calibration.json",
        {"kind": "projector_gamma", "file": str(path), "summary": figs},
        _calibration_lines("gamma", path),
    )


@calibrate_app.command("validate")
def validate_cmd(
    calibration: Path = typer.Argument(..., help="sensor calibration (.yaml) to validate"),
    cell: Path = CellOpt,
    out: Path = OutOpt,
    height_mm: float = 12.5,
    sphere_radius_mm: float = typer.Option(12.5, min=1.0, help="radius of the sphere of the sphere test"),
    seed: int = 2,
) -> None:
    """Flat test at a known height (Table 5.1 figures), plane and sphere fits (a sphere of known radius on the
    reference board) and the gauge slot test with a saved sensor calibration."""
    from cell.calibration.sensor import load_sensor_model
    from cell.calibration.validation import fit_plane, flat_test, slot_test, sphere_test
    from cell.geometry import transform_points
    from cell.mesh import load_mesh
    from cell.sensing.decode import decode
    from cell.sensing.patterns import gcls_patterns
    from fakes.sim.board import BOARD_BASE_Z_MM, SteppedReferenceBoard, sphere_on_board

    cfg = _sim_cell(cell)
    run = _folder(out, cell)
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    model = load_sensor_model(calibration, cam)
    rig = SteppedReferenceBoard(cfg.sensor, cfg.sim)
    ps = gcls_patterns(
        proj.width_px, proj.height_px, 12, 12, "columns", n_gray=6 if proj.width_px >= 768 else None
    )
    rng = np.random.default_rng(seed)
    cloud = model.triangulate(decode(rig.capture(height_mm, ps.frames, rng), ps, cam.bit_depth))
    flat = flat_test(cloud, model.res_mm, height_mm)
    plane = fit_plane(cloud.points_C[cloud.valid])
    ball, centre_W = sphere_on_board(sphere_radius_mm)
    sc = model.triangulate(
        decode(
            rig.renderer(0.0, ball).render_stack(
                rig.T_W_C, list(ps.frames), cam.exposure_ms, cam.gain_db, rng
            ),
            ps,
            cam.bit_depth,
        )
    )
    sp = transform_points(rig.T_W_C, sc.points_C[sc.valid])
    # the board around the foot of the sphere touches it: keep what stands a quarter radius above the board
    sphere = sphere_test(sp[sp[:, 2] > BOARD_BASE_Z_MM + 0.25 * sphere_radius_mm], sphere_radius_mm, centre_W)
    truth = json.loads(GAUGE.with_suffix(".truth.json").read_text())
    lift = np.array([0.0, 0.0, BOARD_BASE_Z_MM - truth["top_z_mm"] / 2])
    gauge = load_mesh(GAUGE).apply_translation(lift)
    r = rig.renderer(-truth["top_z_mm"] / 2, gauge)
    gc = model.triangulate(
        decode(
            r.render_stack(rig.T_W_C, list(ps.frames), cam.exposure_ms, cam.gain_db, rng), ps, cam.bit_depth
        )
    )
    pts = transform_points(rig.T_W_C, gc.points_C[gc.valid]) - lift
    slots = slot_test(pts[pts[:, 2] > truth["top_z_mm"] - 5], truth["slots"])
    _finish(
        run,
        "validation.json",
        {
            "calibration": str(calibration),
            "summary": {"flat": flat, "plane": plane, "sphere": sphere, "slots": slots},
        },
    )


@calibrate_app.command("handeye")
def handeye_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    noise_mm: float = 0.016,
    seed: int = 1,
    force: bool = typer.Option(False, "--force"),
) -> None:
    """Hand-eye T_T_C by ICP of gauge scans against its CAD (dissertation 4.1.3), from three corner views.

    Simulated scans: the simulator's surface points plus NOISE_MM of sensor noise; the start is the configured
    T_T_C (the mounting drawing)."""
    from cell.analysis.errormap import NominalMesh
    from cell.calibration.handeye import GaugeView, handeye_icp, pose_error
    from cell.calibration.store import save_calibration
    from cell.geometry import invert, look_at
    from cell.mesh import load_mesh
    from cell.planning.kinematics import UR5E
    from fakes.sim.render import SceneRenderer
    from fakes.sim.scene import Scene

    cfg = _sim_cell(cell)
    run = _folder(out, cell)
    gauge = load_mesh(GAUGE)
    T_W_P = np.eye(4)
    T_W_P[:3, 3] = (-120.0, 60.0, 0.0)
    renderer = SceneRenderer(
        cfg.sensor, cfg.sim, Scene.from_meshes(gauge.copy().apply_transform(T_W_P), cfg.sim)
    )
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), cfg.sensor.T_T_C.matrix()
    rng = np.random.default_rng(seed)
    centre = T_W_P[:3, 3] + (0.0, 0.0, 15.0)
    views = []
    for az in np.radians([45, 135, 225, 315]):
        eye = centre + cfg.sensor.standoff_mm * np.array(
            [np.sin(0.87) * np.cos(az), np.sin(0.87) * np.sin(az), np.cos(0.87)]
        )
        sols = UR5E.ik(invert(T_W_B) @ look_at(eye, centre) @ invert(T_T_C), allow_singular=False)
        if not sols.ok:
            run.log("view_skipped", azimuth_deg=float(np.degrees(az)), reason=sols.reason)
            continue
        T_B_T = UR5E.fk(sols.joints[0])
        gt = renderer.ground_truth(T_W_B @ T_B_T @ T_T_C)
        p = gt.points_C[gt.hit][::40]
        views.append(GaugeView(p + rng.normal(0, noise_mm, p.shape), T_B_T))
        run.log("view", azimuth_deg=float(np.degrees(az)), points=len(p))
    res = handeye_icp(NominalMesh.from_trimesh(gauge), views, T_W_B, T_W_P, T_T_C)
    dt, dr = pose_error(res.T_T_C, T_T_C)
    figs = {
        "views": len(views),
        "iterations": len(res.cost_mm2),
        "converged": res.converged,
        "rms_mm": res.rms_mm,
        "delta_eq_4_15": res.delta[-5:],
        "change_from_config_mm": dt,
        "change_from_config_deg": dr,
    }
    path = save_calibration(
        run.path / "handeye",
        "hand_eye",
        {"T_T_C": res.T_T_C},
        {"T_T_C": res.T_T_C.tolist(), "figures": figs, "quality": {"rms_mm": res.rms_mm}},
        "quality.rms_mm",
        force,
    )
    _finish(
        run,
        "calibration.json",
        {"kind": "hand_eye", "file": str(path), "summary": figs},
        _calibration_lines("hand_eye", path),
    )


def register(app: typer.Typer) -> None:
    app.add_typer(calibrate_app, name="calibrate")
