"""``cell sensor ...``: sensor model utilities (the one-pixel error tables of the dissertation)."""

from __future__ import annotations

import typer

sensor_app = typer.Typer(help="Structured-light sensor model utilities.", no_args_is_help=True)


@sensor_app.command("error-table")
def error_table_cmd() -> None:
    """Print Tables 2.1-2.3: height error (mm) of a one-pixel error in L (dissertation eq 2.5)."""
    from cell.sensing.error_model import format_tables

    typer.echo(format_tables())


def register(app: typer.Typer) -> None:
    app.add_typer(sensor_app, name="sensor")
