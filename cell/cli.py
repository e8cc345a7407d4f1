"""The ``cell`` command. Each ``cell/commands/<name>.py`` module adds its commands through ``register(app)``.

Commands load on demand: ``cell --help`` lists them from :data:`COMMANDS` without importing any command
module, and ``cell NAME ...`` imports only the module that defines NAME, so start-up stays well under a second
however heavy the library behind a command is (bench/bench_startup.py measures it).

Errors the cell raises on purpose (:class:`cell.errors.CellError`) end the command with one clear line and the
error's exit code (2 for bad input); usage errors (unknown option, missing argument) end the same way with
exit code 2; a disk that is full or read-only ends with one line naming the file (exit code 1); anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

import typer
from typer.core import TyperCommand, TyperGroup

from cell.errors import CellError, RoutinePaused

# name -> (module under cell.commands that registers it, one-line help for `cell --help`).
# tests/test_cli.py checks that this table and the modules' registrations name the same commands.
COMMANDS: dict[str, tuple[str, str]] = {
    "inspect": ("inspect", "Run an inspection recipe end to end; Ctrl-C pauses safely."),
    "resume": ("inspect", "Finish an interrupted or paused run from its last checkpoint."),
    "report": ("inspect", "Rebuild a finished run's report from its stored views."),
    "abort": ("abort", "Mark a paused or interrupted run aborted (it can no longer be resumed)."),
    "history": ("history", "Past runs from the results database, filtered; SPC of a recipe."),
    "prune": ("prune", "Remove raw view images the cell's retention policy no longer keeps."),
    "demo": ("inspect", "A full simulated inspection of the demo pillar, ending in a report."),
    "plan": ("plan", "Plan the viewpoints of a recipe's part and print its cycle-time limit."),
    "scan": ("scan", "One structured-light scan of a mesh in the simulated cell, from one pose."),
    "compare": ("compare", "Error map and report of any cloud against any nominal mesh."),
    "glass": ("glass", "Back-imaging inspection of a glass pane on the glass rig."),
    "calibrate": (
        "calibrate",
        "Calibration routines: sensor, intrinsics, projector, gamma, hand-eye, latency, validate, all.",
    ),
    "verify": ("verify", "VDI/VDE 2634 acceptance test, interim check and verification history."),
    "sensor": ("sensor", "Structured-light sensor model utilities."),
    "devices": ("devices", "Connect each configured device and print its status."),
    "docs": ("docs", "Regenerate the schema pages and the state diagram in docs/ from the code."),
    "station": ("station", "The operator's web application (start, live, verdict, runs, SPC) and its users."),
}


def load_module_commands(module: str) -> dict[str, Any]:
    """Import ``cell.commands.<module>`` and return the click commands its ``register(app)`` adds, by name."""
    sub = typer.Typer(rich_markup_mode=None)
    importlib.import_module(f"cell.commands.{module}").register(sub)
    return dict(typer.main.get_group(sub).commands)


class LazyGroup(TyperGroup):
    """A typer group whose commands are imported the first time they are run or asked for their help."""

    def list_commands(self, ctx: Any) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        if cmd_name in self.commands:
            return self.commands[cmd_name]
        if cmd_name not in COMMANDS:
            return None
        # listing (cell --help) needs only the name and the line of help: a stand-in, no import
        return TyperCommand(name=cmd_name, help=COMMANDS[cmd_name][1])

    def resolve_command(self, ctx: Any, args: list[str]) -> Any:
        name = args[0] if args else None
        if name in COMMANDS and name not in self.commands:
            self.commands.update(load_module_commands(COMMANDS[name][0]))
        return super().resolve_command(ctx, args)


app = typer.Typer(
    name="cell",
    cls=LazyGroup,
    help="Robotic 3D surface inspection cell: scan, plan, inspect, calibrate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain help: typer's rich help formatter alone costs 0.1-0.2 s of imports
)


@app.callback()
def _root() -> None:
    """Robotic 3D surface inspection cell: scan, plan, inspect, calibrate."""


def _fail(message: str, exit_code: int) -> None:
    """One line on stderr, then exit: no traceback for errors a user can fix."""
    from rich.console import Console
    from rich.text import Text

    # Text, not markup: a message quoting user input (a file name with brackets) is printed as it is
    Console(stderr=True).print(
        Text.assemble(("error: ", "bold red"), message), highlight=False, soft_wrap=True
    )
    sys.exit(exit_code)


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``cell`` script: runs the typer app and turns CellError and usage errors into an
    exit code with one line of explanation."""
    try:
        code = app(args=argv, prog_name="cell", standalone_mode=False)
        if isinstance(code, int) and code != 0:  # click returns a command's typer.Exit code, not raises it
            sys.exit(code)
    except RoutinePaused as exc:
        print(f"paused: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except CellError as exc:
        _fail(str(exc), exc.exit_code)
    except OSError as exc:  # a full disk or read-only folder the library did not name: still one line
        from cell.storage import describe, is_storage_error

        if not is_storage_error(exc):
            raise
        _fail(describe(exc), 1)
    except (typer.Abort, KeyboardInterrupt):
        print("aborted", file=sys.stderr)
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # the parser's usage errors (unknown option, missing argument)
        command = getattr(getattr(exc, "ctx", None), "command_path", "cell")
        _fail(f"{exc.format_message()} (see '{command} --help')", getattr(exc, "exit_code", 2))
