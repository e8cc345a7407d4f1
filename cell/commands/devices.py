"""``cell devices``: connect every configured device and print a status table."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer


def describe(kind: str, device: Any) -> str:
    """One line of status for a connected device, read through its contract."""
    from cell.contracts import Camera, Projector, Robot

    if isinstance(device, Robot):
        state = device.state()
        x, y, z = device.tool_pose()[:3, 3]
        stops = [
            n
            for n, on in (("protective stop", state.protective_stop), ("E-stop", state.emergency_stop))
            if on
        ]
        return f"mode {state.mode.value}; flange at ({x:.1f}, {y:.1f}, {z:.1f}) mm" + (
            f"; {', '.join(stops)}" if stops else ""
        )
    if isinstance(device, Projector):
        s = device.status()
        w, h = device.resolution
        errors = f"; errors: {', '.join(s.errors)}" if s.errors else ""
        return (
            f"{w}x{h}; power {'on' if s.powered else 'off'}; source {s.source.value}; "
            f"lamp {s.lamp_hours:.0f} h; {s.temperature_c:.0f} C{errors}"
        )
    if isinstance(device, Camera):
        w, h = device.resolution
        return f"{device.model}, serial {device.serial}, {w}x{h}"
    return type(device).__name__


def register(app: typer.Typer) -> None:
    @app.command("devices")
    def devices(
        cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    ) -> None:
        """Connect each configured device and print its status; exit 1 naming the first device that fails."""
        from rich.console import Console
        from rich.table import Table

        from cell.config import DEFAULT_CELL, load_cell_config
        from cell.devices import build_devices
        from cell.errors import DeviceError

        cell = cell or DEFAULT_CELL
        cfg = load_cell_config(cell)
        bundle = build_devices(cfg)
        table = Table(title=f"cell '{cfg.name}' ({cell})")
        for column in ("device", "kind", "driver", "status"):
            table.add_column(column)
        drivers = {
            "robot": cfg.robot.driver,
            "camera": cfg.sensor.camera.driver,
            "projector": cfg.sensor.projector.driver,
        }
        failures: list[str] = []
        for kind, device in bundle.items():
            name = bundle.names[kind]
            try:
                device.connect()
                status = describe(kind, device)
            except Exception as exc:  # any failure is reported per device, then the command fails
                status = f"[red]FAILED: {exc}[/]"
                detail = str(exc) if isinstance(exc, DeviceError) else f"{name}: {exc}"
                failures.append(f"{kind} '{name}': {detail}")
            table.add_row(name, kind, drivers[kind], status)
        for _, device in bundle.items():
            try:
                device.close()
            except Exception:  # closing a device that failed to connect must not hide the report
                pass
        Console().print(table)
        if failures:
            Console(stderr=True).print("[bold red]error:[/] " + "; ".join(failures), highlight=False)
            raise typer.Exit(1)
