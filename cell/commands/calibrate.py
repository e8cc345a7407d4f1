"""``cell calibrate ...``: argument parsing for the technician's routines (cell.calibration.routines), which
run under the controller on the configured cell's devices and board stage, or, with ``--from``, on a capture
folder (cell.calibration.offline). Each writes a run folder ``--out`` (journal, checkpoint, views,
``calibration.json`` or ``validation.json``) and prints the lines to put into the cell config; it never edits
the config itself. Running a command again on an unfinished ``--out`` resumes it.

This module holds the group and the sensor routines (sensor, intrinsics, projector, gamma);
cell/commands/calibrate_cell.py adds handeye, kinematics, validate and all, cell/commands/latency.py adds
latency; cell/commands/calibrate_common.py holds what they share."""

from __future__ import annotations

from pathlib import Path

import typer

from cell.commands.calibrate_common import (
    CellOpt,
    ForceOpt,
    FromOpt,
    OutOpt,
    cell_config,
    offline,
    run,
    start,
)

calibrate_app = typer.Typer(
    help="Calibration routines: per-pixel sensor, camera intrinsics, projector, projector gamma, hand-eye, "
    "validation, all of them in a row.",
    no_args_is_help=True,
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
    start("sensor", cell, out, source)
    if source is not None:
        return offline("sensor", source, out, cell, force=force, points=points)
    from cell.calibration.sensor_routines import SensorJob

    cfg = cell_config(cell)
    run(SensorJob(cfg, steps=steps, step_mm=step_mm, points=points, force=force, seed=seed), out, cell, seed)


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
    start("intrinsics", cell, out, source)
    if source is not None:
        return offline("intrinsics", source, out, cell, force=force)
    from cell.calibration.sensor_routines import IntrinsicsJob

    run(IntrinsicsJob(cell_config(cell), views=views, force=force, seed=seed), out, cell, seed)


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
    start("projector", cell, out, source)
    if source is not None:
        return offline("projector", source, out, cell, intrinsics=intrinsics, force=force)
    from cell.calibration.sensor_routines import ProjectorJob

    job = ProjectorJob(cell_config(cell), views=views, intrinsics=intrinsics, force=force, seed=seed)
    run(job, out, cell, seed)


@calibrate_app.command("gamma")
def gamma_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    levels: int = typer.Option(17, min=3),
    force: bool = ForceOpt,
    seed: int = 1,
) -> None:
    """Projector response: uniform grey levels on the white board; writes the linearising LUT."""
    start("gamma", cell, out)
    from cell.calibration.sensor_routines import GammaJob

    run(GammaJob(cell_config(cell), levels=levels, force=force, seed=seed), out, cell, seed)


def register(app: typer.Typer) -> None:
    from cell.commands import calibrate_cell
    from cell.commands.latency import latency_cmd

    calibrate_cell.add_to(calibrate_app)
    calibrate_app.command("latency")(latency_cmd)
    app.add_typer(calibrate_app, name="calibrate")
