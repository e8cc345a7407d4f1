"""``cell calibrate handeye|kinematics|validate|all``: the routines that calibrate the robot with the sensor,
validate the sensor's calibration, or chain every routine. Added to the ``calibrate`` group by
cell/commands/calibrate.py, whose options and printing they share."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from cell.commands.calibrate_common import CellOpt, ForceOpt, OutOpt, print_result, run, start


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
    start("handeye", cell, out)
    from cell.calibration.routines import handeye_job
    from cell.config import load_cell_config

    run(handeye_job(load_cell_config(cell), method, views=views, force=force, seed=seed), out, cell, seed)


def kinematics_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    views: int = typer.Option(24, min=8, help="robot poses looking at the still board"),
    force: bool = ForceOpt,
    seed: int = 1,
) -> None:
    """The robot's link-length and joint-zero errors with the hand-eye, from board views (writes
    OUT/kinematics.yaml and the hand-eye found with it, OUT/handeye.yaml; set both in the cell config)."""
    start("kinematics", cell, out)
    from cell.calibration.handeye_routines import KinematicsJob
    from cell.config import load_cell_config

    run(KinematicsJob(load_cell_config(cell), views=views, force=force, seed=seed), out, cell, seed)


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
    seed: int = typer.Option(2, help="simulated cells: the noise seed (with the cell's sim.seed)"),
) -> None:
    """The flat board at --height-mm above the reference plane, a sphere of known radius and the slot gauge
    on the stage, measured with the cell's active calibration (or CALIBRATION): plane height error and
    residual, the flat test (Table 5.1), sphere radius error and residual, slot depths against the gauge's
    certificate (Fig 5.4)."""
    start("validate", cell, out)
    from cell.calibration.routines import run_validation

    result = run_validation(
        cell,
        out,
        calibration,
        gauge,
        seed=seed,
        height_mm=height_mm,
        sphere_radius_mm=sphere_radius_mm,
        gauge_height_mm=gauge_height_mm,
    )
    print_result(result)


def all_cmd(
    cell: Path = CellOpt,
    out: Path = OutOpt,
    sensor: bool = typer.Option(False, "--sensor", help="also the per-pixel sensor model (31 board steps)"),
    seed: int = 1,
) -> None:
    """Intrinsics, projector, robot kinematics with the hand-eye (board poses), optionally the per-pixel
    sensor, then validation; writes OUT/cell.yaml that uses them."""
    start("all", cell, out)
    from cell.calibration.routines import calibrate_all

    cell_out, summary = calibrate_all(cell, out, sensor=sensor, seed=seed, say=typer.echo)
    typer.echo(json.dumps({k: v.get("summary", v) for k, v in summary.items()}, indent=2, default=str))
    typer.echo(f"\nCalibrated cell config: {cell_out} (use it with --cell)")


def add_to(group: typer.Typer) -> None:
    """Add this module's commands to the ``calibrate`` group, after the sensor routines."""
    for name, command in (
        ("handeye", handeye_cmd),
        ("kinematics", kinematics_cmd),
        ("validate", validate_cmd),
        ("all", all_cmd),
    ):
        group.command(name)(command)
