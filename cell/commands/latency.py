"""``cell calibrate latency``: measure the display latency on the configured cell (real or simulated) and
write it as a calibration file (cell.calibration.latency). Added to the ``calibrate`` group by
cell/commands/calibrate.py."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from cell.defaults import DEFAULT_CELL


def latency_cmd(
    cell: Path = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML"),
    out: Path = typer.Option(..., "--out", help="folder to write latency.yaml/.npz into"),
    max_frames: float = typer.Option(8.0, min=1.0, help="longest delay tried, in refresh periods"),
    steps_per_frame: int = typer.Option(4, min=1, help="delays tried per refresh period"),
    force: bool = typer.Option(False, "--force", help="replace an existing latency file"),
) -> None:
    """Display latency: show black then white, trigger the camera at growing delays after the present stamp;
    the sensor must look at a matte surface the projector lights (the robot is not moved)."""
    typer.echo(f"calibrate latency: cell {cell} -> {out}")
    from cell.calibration.latency import calibrate_latency
    from cell.calibration.store import config_lines
    from cell.config import load_cell_config

    path, meta = calibrate_latency(
        load_cell_config(cell), out, max_frames=max_frames, steps_per_frame=steps_per_frame, force=force
    )
    typer.echo(json.dumps({k: meta[k] for k in ("latency_ms", "figures")}, indent=2)[:2000])
    typer.echo(f"\nTo use it, put this into the cell config:\n{config_lines('display_latency', path)}")
