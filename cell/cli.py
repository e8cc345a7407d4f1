"""The ``cell`` command. Each ``cell/commands/<name>.py`` module adds its commands through ``register(app)``.

Commands load on demand: ``cell --help`` prints the list from :data:`COMMANDS` without importing typer or any
command module (:func:`root_help` writes what typer would), and ``cell NAME ...`` imports typer and only the
module that defines NAME, whose heavy imports wait inside the command; typer converts option values without
pydantic (:mod:`cell.cli_coercion`). So a command's help, a usage error or a command's first line comes
within about 0.1-0.2 s of CPU however heavy the library behind it is (bench/bench_startup.py measures it).

Errors the cell raises on purpose (:class:`cell.errors.CellError`) end the command with one clear line and the
error's exit code (2 for bad input); usage errors (unknown option, missing argument) end the same way with
exit code 2; a disk that is full or read-only ends with one line naming the file (exit code 1); anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

import importlib
import sys
from functools import cache
from typing import TYPE_CHECKING, Any

from cell.errors import CellError, RoutinePaused

if TYPE_CHECKING:
    import typer

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


ROOT_HELP = "Robotic 3D surface inspection cell: scan, plan, inspect, calibrate."


def load_module_commands(module: str) -> dict[str, Any]:
    """Import ``cell.commands.<module>`` and return the click commands its ``register(app)`` adds, by name."""
    import typer

    sub = typer.Typer(rich_markup_mode=None)
    importlib.import_module(f"cell.commands.{module}").register(sub)
    return dict(typer.main.get_group(sub).commands)


@cache
def build_app() -> typer.Typer:
    """The typer application: a group whose commands are imported the first time they are run or asked for
    their help (built on first use: ``cell --help`` does without typer)."""
    import typer
    from typer.core import TyperCommand, TyperGroup

    from cell import cli_coercion

    cli_coercion.install()  # option values without pydantic's import (0.15 s of CPU of every command's start)

    class LazyGroup(TyperGroup):
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
        help=ROOT_HELP,
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        rich_markup_mode=None,  # plain help: typer's rich help formatter alone costs 0.1-0.2 s of imports
    )

    @app.callback()
    def _root() -> None:
        """Robotic 3D surface inspection cell: scan, plan, inspect, calibrate."""

    return app


def __getattr__(name: str) -> Any:
    if name == "app":  # ``from cell.cli import app`` (tests drive it with typer's CliRunner)
        return build_app()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def short_help(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters at a word, as click lists a command (a sentence's full stop
    ends it, a cut ends in "...")."""
    words = text.split()
    total = 0
    for i, word in enumerate(words):
        total += len(word) + (i > 0)
        if total > limit:
            break
        if word.endswith("."):
            return " ".join(words[: i + 1])
        if total == limit and i != len(words) - 1:
            break
    else:
        return " ".join(words)
    total += 3
    while i > 0:
        total -= len(words[i]) + 1
        if total <= limit:
            break
        i -= 1
    return " ".join(words[:i]) + "..."


def root_help(width: int | None = None) -> str:
    """``cell --help`` as typer prints it (tests/test_cli.py compares the two), from :data:`COMMANDS` alone:
    no typer, no command module. ``width``: of the text, by default click's (the terminal's, 50..78)."""
    import shutil
    import textwrap

    if width is None:
        width = max(min(shutil.get_terminal_size().columns, 80) - 2, 50)
    name_w = max(len(name) for name in COMMANDS)
    first_col = min(name_w, 30) + 2
    text_w = max(width - first_col - 2, 10)
    lines = [
        "Usage: cell [OPTIONS] COMMAND [ARGS]...",
        "",
        textwrap.fill(ROOT_HELP, width, initial_indent="  ", subsequent_indent="  "),
        "",
        "Options:",
        "  --help  Show this message and exit.",
        "",
        "Commands:",
    ]
    for name, (_, text) in COMMANDS.items():
        wrapped = textwrap.wrap(short_help(text, width - 6 - name_w), text_w) or [""]
        lines.append(f"  {name:<{first_col - 2}}  {wrapped[0]}")
        lines += [" " * (first_col + 2) + more for more in wrapped[1:]]
    return "\n".join(lines) + "\n"


def _fail(message: str, exit_code: int) -> None:
    """One line on stderr, then exit: no traceback for errors a user can fix. Written as it is (a message
    quoting user input, a file name with brackets, stays intact); "error:" in bold red on a terminal."""
    import os

    colour = sys.stderr.isatty() and "NO_COLOR" not in os.environ and os.environ.get("TERM") != "dumb"
    sys.stderr.write(("\x1b[1;31merror:\x1b[0m " if colour else "error: ") + message + "\n")
    sys.stderr.flush()
    sys.exit(exit_code)


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``cell`` script: runs the typer app and turns CellError and usage errors into an
    exit code with one line of explanation."""
    if (sys.argv[1:] if argv is None else list(argv)) == ["--help"]:
        sys.stdout.write(root_help())
        return
    import typer

    try:
        code = build_app()(args=argv, prog_name="cell", standalone_mode=False)
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
