"""``cell calibrate sensor|intrinsics|projector|gamma|handeye|validate|all``: argument parsing for the
technician's routines (cell.calibration.routines), which run under the controller on the configured cell's
devices and board stage. Each writes a run folder ``--out`` (journal, checkpoint, views, ``calibration.json``
or ``validation.json``) and prints the lines to put into the cell config; it never edits the config itself.
Running a command again on an unfinished ``--out`` resumes it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from cell.config import DEFAULT_CELL, load_cell_config

calibrate_app = typer.Typer(
    help="Calibration routines: per-pixel sensor, camera intrinsics, projector, projector gamma, hand-eye, "
    "validation, all of them in a row.",
    no_args_is_help=True,
)
CellOpt = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML")
OutOpt = typer.Option(..., "--out", help="run folder to write (an unfinished one is resumed)")
ForceOpt = typer.Option(False, "--force", help="replace a better existing calibration")
FromOpt = typer.Option(
    None,
    "--from",
    help="capture folder of images taken elsewhere (docs/capture-folders.md); no device is used",
)
FIELDS = {
    "camera_intrinsics": "intrinsics",
    "projector": "projector",
    "projector_gamma": "gamma",
    "sensor_per_pixel": "sensor",
    "hand_eye": "hand_eye",
}


def _run(job: Any, out: Path, cell: Path, seed: int, inputs: dict[str, Path] | None = None) -> None:
    from cell.calibration.routines import run_routine

    result = run_routine(job, out, cell, seed=seed, inputs=inputs)
    typer.echo(json.dumps(result.get("summary", result), indent=2, default=str))
    field = FIELDS.get(result.get("kind", ""))
    if field:
        typer.echo(
            "\nTo use it, put this into the cell config (paths may be made relative to the cell file):\n"
            f"calibration:\n  {field}: {Path(result['file']).resolve()}"
        )


def _offline(routine: str, source: Path, out: Path, cell: Path, **kw: Any) -> None:
    """``--from SOURCE``: the routine on a capture folder (cell.calibration.offline), no device involved."""
    from cell.calibration.capture_folder import MANIFEST, load_capture_folder
    from cell.calibration.offline import run_offline
    from cell.runs import RunFolder, write_json_atomic

    folder = load_capture_folder(source)  # checked before the run folder is made
    if (out / "journal.jsonl").exists():
        run = RunFolder.open(out)
    else:
        run = RunFolder.create(out.parent, "calibration", name=out.name)
    run.copy_input(cell, "cell.yaml")
    run.copy_input(source / MANIFEST, MANIFEST)
    kind, path, figs = run_offline(routine, folder, run.path, cell, **kw)
    report = {"kind": kind, "file": str(path), "source": str(source), "summary": figs}
    field = FIELDS.get(kind, kind)
    report["cell_config_lines"] = f"calibration:\n  {field}: {Path(path).resolve()}"
    write_json_atomic(run.path / "calibration.json", report)
    run.log("done", report="calibration.json")
    typer.echo(json.dumps(figs, indent=2, default=str))
    typer.echo(
        "\nTo use it, put this into the cell config (paths may be made relative to the cell file):\n"
        + report["cell_config_lines"]
    )


@calibrate_app.command("sensor")
def sensor_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    steps: int = typer.Option(30, min=3),
    step_mm: float = typer.Option(1.0, min=0.01),
    points: int = typer.Option(65536, min=16),
    force: bool = ForceOpt,
    seed: int = 1,
    source: Path | None = FromOpt,
) -> None:
    """Per-pixel calibration: the stage steps the reference board STEPS x STEP_MM toward the sensor
    (dissertation 5.1.1)."""
    if source is not None:
        return _offline("sensor", source, out, cell, force=force, points=points)
    from cell.calibration.routines import SensorJob

    job = SensorJob(
        load_cell_config(cell), steps=steps, step_mm=step_mm, points=points, force=force, seed=seed
    )
    _run(job, out, cell, seed)


@calibrate_app.command("intrinsics")
def intrinsics_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    views: int = typer.Option(12, min=1),
    force: bool = ForceOpt,
    seed: int = 1,
    source: Path | None = FromOpt,
) -> None:
    """Camera K and distortion from VIEWS images of a ChArUco board the stage holds (OpenCV)."""
    if source is not None:
        return _offline("intrinsics", source, out, cell, force=force)
    from cell.calibration.routines import IntrinsicsJob

    _run(IntrinsicsJob(load_cell_config(cell), views=views, force=force, seed=seed), out, cell, seed)


@calibrate_app.command("projector")
def projector_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    views: int = typer.Option(6, min=1),
    intrinsics: Path | None = typer.Option(
        None, help="camera intrinsics file; default: the cell's active camera (calibration.intrinsics)"
    ),
    force: bool = ForceOpt,
    seed: int = 1,
    source: Path | None = FromOpt,
) -> None:
    """Projector K and T_C_P (Moreno-Taubin local homographies at the ChArUco corners, stereoCalibrate)."""
    if source is not None:
        return _offline("projector", source, out, cell, intrinsics=intrinsics, force=force)
    from cell.calibration.routines import ProjectorJob

    job = ProjectorJob(load_cell_config(cell), views=views, intrinsics=intrinsics, force=force, seed=seed)
    _run(job, out, cell, seed)


@calibrate_app.command("gamma")
def gamma_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    levels: int = typer.Option(17, min=3),
    force: bool = ForceOpt,
    seed: int = 1,
) -> None:
    """Projector response: uniform grey levels on the white board; writes the linearising LUT."""
    from cell.calibration.routines import GammaJob

    _run(GammaJob(load_cell_config(cell), levels=levels, force=force, seed=seed), out, cell, seed)


@calibrate_app.command("handeye")
def handeye_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    method: str = typer.Option(
        "icp", help="icp (gauge scans, dissertation 4.1.3) or tsai|park|daniilidis (board poses)"
    ),
    views: int = typer.Option(12, min=3, help="robot poses for the board methods"),
    force: bool = ForceOpt,
    seed: int = 1,
) -> None:
    """Hand-eye T_T_C: ICP of gauge scans against its CAD from the mounting drawing, or AX = XB from board
    poses."""
    from cell.calibration.routines import HandEyeBoardJob, HandEyeIcpJob
    from cell.errors import ConfigError

    cfg = load_cell_config(cell)
    if method == "icp":
        job: Any = HandEyeIcpJob(cfg, force=force, seed=seed)
    elif method in ("tsai", "park", "daniilidis"):
        job = HandEyeBoardJob(cfg, views=views, method=method, force=force, seed=seed)
    else:
        raise ConfigError(
            f"unknown hand-eye method '{method}': use icp, tsai, park or daniilidis", field="method"
        )
    _run(job, out, cell, seed)


@calibrate_app.command("kinematics")
def kinematics_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    views: int = typer.Option(24, min=8, help="robot poses looking at the still board"),
    force: bool = ForceOpt,
    seed: int = 1,
) -> None:
    """The robot's link-length and joint-zero errors with the hand-eye, from board views (writes
    OUT/kinematics.yaml and the hand-eye found with it, OUT/handeye.yaml; set both in the cell config)."""
    from cell.calibration.routines import KinematicsJob

    _run(KinematicsJob(load_cell_config(cell), views=views, force=force, seed=seed), out, cell, seed)


@calibrate_app.command("validate")
def validate_cmd(
    calibration: Path | None = typer.Argument(None, help="a sensor calibration (.yaml) to validate instead"),
    cell: Path = CellOpt,
    out: Path = OutOpt,
    height_mm: float = typer.Option(12.5, help="the flat board's height above the reference plane (mm)"),
    sphere_radius_mm: float = typer.Option(12.5, min=1.0, help="radius of the sphere of the sphere test"),
    gauge: Path = typer.Option(
        None,
        "--gauge",
        help="the slot gauge's certificate (YAML; default recipes/parts/gauge.certificate.yaml)",
    ),
    gauge_height_mm: float = typer.Option(15.0, help="the gauge's top above the reference plane (mm)"),
    seed: int = typer.Option(2, help="simulated cells: the camera noise seed"),
) -> None:
    """The flat board at --height-mm above the reference plane, a sphere of known radius and the slot gauge
    on the stage, measured with the cell's active calibration (or CALIBRATION): plane height error and
    residual, the flat test (Table 5.1), sphere radius error and residual, slot depths against the gauge's
    certificate (Fig 5.4)."""
    from cell.calibration.routines import ValidateJob
    from cell.errors import ConfigError

    cfg = load_cell_config(cell)
    if calibration is not None:
        if not calibration.is_file():
            raise ConfigError("sensor calibration file not found; check the path", path=str(calibration))
        cfg.calibration.sensor = calibration.resolve()
    from cell.calibration.procedures import GAUGE_CERTIFICATE

    gauge = gauge or GAUGE_CERTIFICATE
    job = ValidateJob(
        cfg,
        height_mm=height_mm,
        sphere_radius_mm=sphere_radius_mm,
        gauge_height_mm=gauge_height_mm,
        seed=seed,
        gauge_certificate=gauge,
    )
    _run(job, out, cell, seed, inputs={"gauge.certificate.yaml": gauge})


@calibrate_app.command("all")
def all_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    sensor: bool = typer.Option(False, "--sensor", help="also the per-pixel sensor model (31 board steps)"),
    seed: int = 1,
) -> None:
    """Intrinsics, projector, robot kinematics with the hand-eye (board poses), optionally the per-pixel
    sensor, then validation; writes OUT/cell.yaml that uses them."""
    from cell.calibration.routines import calibrate_all

    cell_out, summary = calibrate_all(cell, out, sensor=sensor, seed=seed, say=typer.echo)
    typer.echo(json.dumps({k: v.get("summary", v) for k, v in summary.items()}, indent=2, default=str))
    typer.echo(f"\nCalibrated cell config: {cell_out} (use it with --cell)")


def register(app: typer.Typer) -> None:
    from cell.commands.latency import latency_cmd

    calibrate_app.command("latency")(latency_cmd)
    app.add_typer(calibrate_app, name="calibrate")
