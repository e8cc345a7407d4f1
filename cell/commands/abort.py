"""``cell abort DIR``: end a paused or interrupted inspection run for good, through the controller's state
machine (:func:`cell.inspection_run.abort_run`); the station's Abort button does the same."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("abort")
    def abort_cmd(
        run_dir: Path = typer.Argument(..., help="run folder of a paused or interrupted inspection"),
        reason: str = typer.Option("aborted at the terminal", "--reason", help="why, for the journal"),
    ) -> None:
        """Mark a paused or interrupted run aborted (it can no longer be resumed; its files stay). A running
        run is refused: pause it first (Ctrl-C)."""
        typer.echo(f"aborting the run in {run_dir}")
        from cell.inspection_run import abort_run

        typer.echo(f"{abort_run(run_dir, reason)}: {run_dir}")
