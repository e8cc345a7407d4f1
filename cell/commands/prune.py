"""``cell prune``: remove the raw view images that the retention policy no longer keeps (cell.retention)."""

from __future__ import annotations

from pathlib import Path

import typer

from cell.defaults import RUNS_ROOT


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def register(app: typer.Typer) -> None:
    @app.command("prune")
    def prune_cmd(
        runs: Path = typer.Option(RUNS_ROOT, "--runs", help="runs root whose run folders are pruned"),
        cell: Path = typer.Option(
            None,
            "--cell",
            help="apply this cell config's retention: section to every run (default: each run's own, "
            "from the cell config it was made with)",
        ),
        dry_run: bool = typer.Option(False, "--dry-run", help="print what would be removed; change nothing"),
    ) -> None:
        """Remove the raw view images of finished inspection runs older than the retention policy keeps them
        (results, inputs, journal and decoded views are always kept; running or unfinished runs untouched)."""
        typer.echo(f"{'dry run: ' if dry_run else ''}pruning the raw view images of the runs in {runs}")
        from rich.console import Console

        from cell.retention import prune

        policy = None
        if cell is not None:
            from cell.config import load_cell_config

            policy = load_cell_config(cell).retention
        report = prune(runs, policy, dry_run=dry_run)
        console = Console(highlight=False, soft_wrap=True)
        verb = "would remove" if dry_run else "removed"
        for r in report.runs:
            if r.action == "delete":
                done = r.raw_bytes if dry_run else r.freed_bytes
                console.print(f"{verb} {_mb(done):>9}  {r.run.name}  ({r.reason})", markup=False)
            elif r.raw_dirs:
                console.print(f"kept {_mb(r.raw_bytes):>12}  {r.run.name}  ({r.reason})", markup=False)
        total = report.to_free_bytes if dry_run else report.freed_bytes
        n = sum(r.action == "delete" for r in report.runs)
        lead = "dry run: " if dry_run else ""
        console.print(f"{lead}{verb} {_mb(total)} of raw view images from {n} run(s) in {runs}", markup=False)
