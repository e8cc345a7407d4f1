"""``cell scan``: one structured-light scan of a mesh in the simulated cell, from one pose."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from cell.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray


def _parse_pose(text: str) -> NDArray[np.float64] | None:
    """``--pose``: a camera pose T_W_C from x,y,z,rx,ry,rz, or None for 'auto'."""
    from cell.geometry import pose_from_xyz_rotvec

    if text == "auto":
        return None
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 6:
        raise ConfigError(
            f"--pose '{text}': give 'auto' or six numbers x,y,z,rx,ry,rz (camera pose T_W_C: "
            "mm and a rotation vector in rad)",
            field="--pose",
        )
    return pose_from_xyz_rotvec(values[:3], values[3:])


def scan_cmd(
    out: Path = typer.Option(..., "--out", help="output folder (created; must not hold files)"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    part: Path = typer.Option(
        None, "--part", help="part mesh in world coordinates, mm (default: empty table)"
    ),
    pose: str = typer.Option(
        "auto", "--pose", help="'auto' or x,y,z,rx,ry,rz of the camera frame in {W} (mm, rotation vector rad)"
    ),
    codec: str = typer.Option("gcls", "--codec", help="gcls or gcps"),
    model: str = typer.Option("pinhole", "--model", help="triangulation: pinhole or reference (eq 2.8)"),
    seed: int = typer.Option(None, "--seed", help="noise seed (default: the cell's sim.seed)"),
    source: Path = typer.Option(
        None, "--from", help="capture folder (docs/capture-folders.md): scan its poses"
    ),
) -> None:
    """Scan MESH from one pose; write cloud.ply (world mm), masks.png and scan.json to OUT."""
    from cell.defaults import DEFAULT_CELL
    from cell.runs import require_empty_output

    what = f"the capture folder {source}" if source is not None else f"{part or 'the empty table'}"
    typer.echo(f"scanning {what} on cell {cell or DEFAULT_CELL} -> {out}")

    require_empty_output(out)
    if source is not None:  # images captured elsewhere, measured with the cell's active calibration
        from cell.calibration.offline import write_folder_scan
        from cell.config import load_cell_config

        summary = write_folder_scan(load_cell_config(cell or DEFAULT_CELL), source, Path(out))
        return typer.echo(f"{len(summary['poses'])} poses -> {out}")
    from cell.scan_run import scan_in_cell

    summary = scan_in_cell(cell or DEFAULT_CELL, part, _parse_pose(pose), codec, model, Path(out), seed=seed)
    c = summary["counts"]
    counts = ", ".join(f"{k} {v}" for k, v in c.items() if k != "valid")
    typer.echo(f"{c['valid']} points -> {Path(out) / 'cloud.ply'} ({counts})")


def register(app: typer.Typer) -> None:
    app.command("scan")(scan_cmd)
