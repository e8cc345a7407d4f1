"""``cell calibrate latency``: measure the display latency on the configured cell (real or simulated) and
write it as a calibration file. Added to the ``calibrate`` group by cell/commands/calibrate.py."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from cell.config import DEFAULT_CELL, load_cell_config
from cell.contracts import CameraSettings, PixelFormat, ProjectorSource, TriggerMode


def latency_cmd(
    cell: Path = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML"),
    out: Path = typer.Option(..., "--out", help="folder to write latency.yaml/.npz into"),
    max_frames: float = typer.Option(8.0, min=1.0, help="longest delay tried, in refresh periods"),
    steps_per_frame: int = typer.Option(4, min=1, help="delays tried per refresh period"),
    force: bool = typer.Option(False, "--force", help="replace an existing latency file"),
) -> None:
    """Display latency: show black then white, trigger the camera at growing delays after the present stamp;
    the sensor must look at a matte surface the projector lights (the robot is not moved)."""
    from cell.calibration.latency import KIND, latency_meta, measure_latency
    from cell.calibration.store import save_calibration
    from cell.devices import build_devices

    cfg = load_cell_config(cell)
    devices = build_devices(cfg)
    cam = cfg.sensor.camera
    try:
        for _, device in devices.items():
            device.connect()
        devices.projector.set_power(True)
        devices.projector.set_source(ProjectorSource.HDMI)
        fmt = PixelFormat.MONO8 if cam.bit_depth == 8 else PixelFormat(f"Mono{cam.bit_depth}")
        got = devices.camera.configure(
            CameraSettings(cam.exposure_ms, cam.gain_db, fmt, TriggerMode.SOFTWARE)
        )
        m = measure_latency(
            devices.camera,
            devices.projector,
            exposure_ms=got.exposure_ms,
            max_frames=max_frames,
            steps_per_frame=steps_per_frame,
        )
    finally:
        for _, device in reversed(devices.items()):
            device.close()
    out.mkdir(parents=True, exist_ok=True)
    meta = latency_meta(m, cfg.sensor.projector)
    path = save_calibration(
        out / "latency", KIND, {"delays_s": m.delays_s, "white_share": m.white_share}, meta, force=force
    )
    typer.echo(json.dumps({k: meta[k] for k in ("latency_ms", "figures")}, indent=2)[:2000])
    typer.echo(f"\nTo use it, put this into the cell config:\ncalibration:\n  latency: {path.resolve()}")
