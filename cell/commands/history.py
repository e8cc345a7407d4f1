"""``cell history``: the runs of a part from the runs root's index (cell.runs.RunIndex), as a table."""

from __future__ import annotations

from pathlib import Path

import typer

from cell.runs import RUNS_ROOT

COLUMNS = ("started", "part", "status", "verdict", "points", "coverage", "dev min", "dev max", "folder")


def _figure(value: float | None, fmt: str = "{:.3f}") -> str:
    return "" if value is None else fmt.format(value)


def register(app: typer.Typer) -> None:
    @app.command("history")
    def history_cmd(
        part: str = typer.Argument(None, help="part name (default: all parts)"),
        runs: Path = typer.Option(RUNS_ROOT, "--runs", help="runs root holding index.sqlite"),
    ) -> None:
        """List the runs of a part: time, status, verdict and key figures."""
        from rich.console import Console
        from rich.table import Table

        from cell.runs import RunIndex

        table = Table(title=f"runs of {part or 'all parts'} in {runs}")
        for column in COLUMNS:
            table.add_column(column)
        for r in RunIndex(runs).history(part):
            table.add_row(
                r["started"],
                r["part"],
                r["status"],
                r["verdict"] or "",
                _figure(r["n_points"], "{}"),
                _figure(r["coverage"]),
                _figure(r["dev_min"]),
                _figure(r["dev_max"]),
                r["folder"],
            )
        Console().print(table)
