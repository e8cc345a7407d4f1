"""The ``cell`` command. Each ``cell/commands/<name>.py`` module adds its commands through ``register(app)``.

Errors the cell raises on purpose (:class:`cell.errors.CellError`) end the command with one clear line and the
error's exit code (2 for bad input); anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

import typer
from rich.console import Console

import cell.commands
from cell.errors import CellError

app = typer.Typer(
    name="cell",
    help="Robotic 3D surface inspection cell: scan, plan, inspect, calibrate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
err_console = Console(stderr=True)


def _register_commands() -> None:
    for info in sorted(pkgutil.iter_modules(cell.commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"cell.commands.{info.name}")
        module.register(app)


_register_commands()


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``cell`` script: runs the typer app and turns CellError into an exit code."""
    try:
        app(args=argv, standalone_mode=False)
    except CellError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        err_console.print("aborted")
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except Exception as exc:  # click usage errors arrive as ClickException subclasses
        import click

        if isinstance(exc, click.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        raise
