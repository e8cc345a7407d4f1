"""``cell devices``: connect every configured device (cell.devices.check_devices) and print a status table."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("devices")
    def devices(
        cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    ) -> None:
        """Connect each configured device and print its status; exit 1 naming the first device that fails."""
        from cell.defaults import DEFAULT_CELL

        typer.echo(f"connecting the devices of {cell or DEFAULT_CELL}")
        from rich.console import Console
        from rich.table import Table

        from cell.config import load_cell_config
        from cell.devices import check_devices
        from cell.errors import DeviceError

        cell = cell or DEFAULT_CELL
        cfg = load_cell_config(cell)
        checks = check_devices(cfg)
        table = Table(title=f"cell '{cfg.name}' ({cell})")
        for column in ("device", "kind", "driver", "status"):
            table.add_column(column)
        failures: list[str] = []
        for c in checks:
            status = c.status
            if c.error is not None:
                status = f"[red]FAILED: {c.error}[/]"
                detail = str(c.error) if isinstance(c.error, DeviceError) else f"{c.name}: {c.error}"
                failures.append(f"{c.kind} '{c.name}': {detail}")
            table.add_row(c.name, c.kind, c.driver, status)
        Console().print(table)
        if failures:
            Console(stderr=True).print("[bold red]error:[/] " + "; ".join(failures), highlight=False)
            raise typer.Exit(1)
