"""``cell history``: past runs from the results database (cell.results), filtered; its SPC of a recipe;
``--sync`` and ``--rebuild`` bring the database up to date with the run folders."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import typer

from cell.defaults import RUNS_ROOT


def _since(text: str | None) -> datetime | None:
    """``--since`` as an aware datetime: ``YYYY-MM-DD`` or an ISO time, local time unless it says."""
    if text is None:
        return None
    from cell.errors import ConfigError

    try:
        t = datetime.fromisoformat(text)
    except ValueError:
        raise ConfigError(
            f"{text!r} is not a date: YYYY-MM-DD or YYYY-MM-DDTHH:MM", field="--since"
        ) from None
    return t if t.tzinfo else t.astimezone()


def results_db_label(runs: Path, cell: Path | None) -> str:
    """Which results database a query command reads, said before it is opened: the cell config's (named by
    the config file, which is not read yet) or the runs root's results.sqlite."""
    return f"the results database of cell {cell}" if cell else f"{runs / 'results.sqlite'}"


def _intent(runs: Path, cell: Path | None, *, sync: bool, rebuild: bool, spc: str | None) -> str:
    """The command's first line: what it is about to do and which database (:func:`results_db_label`)."""
    db = results_db_label(runs, cell)
    if rebuild:
        return f"rebuilding {db} from the run folders in {runs}"
    if sync:
        return f"recording the runs in {runs} that are waiting for {db}"
    if spc:
        return f"SPC of recipe {spc!r} from {db}"
    return f"past runs in {db}, newest first"


def register(app: typer.Typer) -> None:
    @app.command("history")
    def history_cmd(
        part_arg: str = typer.Argument(None, metavar="[PART]", help="part name (default: all parts)"),
        part: str = typer.Option(None, "--part", help="only this part (same as PART)"),
        serial: str = typer.Option(None, "--serial", help="only this serial number"),
        verdict: str = typer.Option(None, "--verdict", help="only this verdict: pass, fail, incomplete"),
        operator: str = typer.Option(None, "--operator", help="only this operator"),
        since: str = typer.Option(None, "--since", help="only runs started at or after (YYYY-MM-DD)"),
        limit: int = typer.Option(50, "--limit", min=1, help="at most this many runs, newest first"),
        folders: bool = typer.Option(False, "--folders", help="add each run's folder (wider than 80)"),
        runs: Path = typer.Option(RUNS_ROOT, "--runs", help="runs root (its results.sqlite by default)"),
        cell: Path = typer.Option(None, "--cell", help="cell config whose results_db to read"),
        sync: bool = typer.Option(False, "--sync", help="only record the runs still waiting for the db"),
        rebuild: bool = typer.Option(False, "--rebuild", help="rebuild the database from the run folders"),
        spc: str = typer.Option(None, "--spc", metavar="RECIPE", help="SPC of a recipe: Cp/Cpk, trends"),
        csv: Path = typer.Option(None, "--csv", help="with --spc: write the trend table to this CSV file"),
    ) -> None:
        """Past runs, newest first: time, part, serial, operator, verdict and deviation range (mm).

        The runs come from the results database (results.sqlite in the runs root, or the cell config's
        results_db). Runs the database missed while it was down are recorded first.
        """
        # what it reads, before the database layer's import (SQLAlchemy: 0.2 s of CPU) and the query
        typer.echo(_intent(runs, cell, sync=sync, rebuild=rebuild, spc=spc))
        from cell.results import open_results
        from cell.results.text import history_lines, spc_lines

        cfg = None
        if cell:
            from cell.config import load_cell_config

            cfg = load_cell_config(cell)
        store = open_results(cfg, runs)
        if rebuild:
            n = store.rebuild(say=typer.echo)
            typer.echo(f"rebuilt {store.where} from {n} run folders in {runs}")
            return
        n = store.sync()
        if n or sync:
            typer.echo(f"recorded {n} run(s) that were waiting for {store.where}")
        if sync:
            return
        if spc:
            result = store.spc(spc)
            if not result.n_runs:
                typer.echo(f"no finished runs of recipe {spc!r} in {store.where} (recipes are named by file)")
                return
            typer.echo("\n".join(spc_lines(result)))
            if csv:
                csv.write_text(store.spc_csv(spc))
                capability = csv.with_name(csv.stem + "-capability.csv")
                capability.write_text(store.spc_csv(spc, "capability"))
                typer.echo(f"trend: {csv}\ncapability: {capability}")
            return
        rows = store.runs(
            part=part or part_arg,
            serial=serial,
            verdict=verdict,
            operator=operator,
            since=_since(since),
            limit=limit,
        )
        if not rows:
            given = {"part": part or part_arg, "serial": serial, "verdict": verdict, "operator": operator}
            filters = ", ".join(f"{k} {v}" for k, v in {**given, "since": since}.items() if v)
            typer.echo(f"no runs{' with ' + filters if filters else ''} in {store.where}")
            typer.echo(
                "`cell inspect` records every run there"
                + ("" if cell else "; for a cell's PostgreSQL: --cell")
            )
            return
        typer.echo("\n".join(history_lines(rows, folders)))
        if len(rows) == limit:
            typer.echo(f"(the newest {limit}; --limit shows more)")
