"""``cell inspect``, ``cell resume``, ``cell report`` and ``cell demo``: argument parsing and printing around
the run lifecycle of :mod:`cell.inspection_run`. Each exits with the code of its outcome
(:class:`cell.exit_codes.ExitCode`: pass 0, fault 1, bad input 2, paused 3, fail 4, incomplete 5)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from cell.defaults import DEFAULT_CELL, DEMO_CELL, RUNS_ROOT
from cell.exit_codes import ExitCode, for_run

if TYPE_CHECKING:
    from cell.controller import Controller
    from cell.inspection_run import RunOutcome


_say = typer.echo  # progress and the run's messages, as plain lines


def _progress(ctl: Controller) -> None:
    elapsed = time.monotonic() - ctl.progress.started
    done, total = ctl.views_done, ctl.views_total
    remaining = ""
    times = ctl.progress.view_times
    if len(times) >= 2 and total > done:
        per_view = (times[-1] - times[0]) / (len(times) - 1)
        remaining = f", ~{per_view * (total - done):.0f} s left"
    view = ""
    if ctl.current_view is not None and ctl.state.startswith("scanning"):
        view = f" | view {ctl.current_view + 1} of {total}, {done} decoded"
    _say(f"[{elapsed:6.1f} s] {ctl.state}{view}{remaining}")


def verdict_reasons_lines(report_json: Path) -> list[str]:
    """Why an INCOMPLETE or FAIL verdict is what it is, one indented line each: the reasons report.html
    gives first (:func:`cell.analysis.report_html.verdict_reasons`: the report's ``incomplete_reasons``, the
    coverage or region that fell short; the worst out-of-tolerance region and the failed user regions). []
    for a pass, or when the run has no report.json."""
    import json

    if not report_json.is_file():
        return []
    doc = json.loads(report_json.read_text(encoding="utf-8"))
    if doc.get("verdict") not in ("incomplete", "fail"):
        return []
    from cell.analysis.report_html import verdict_reasons

    return [f"  - {reason}" for reason in dict.fromkeys(verdict_reasons(doc))]  # each once


def _finish(outcome: RunOutcome) -> None:
    """The verdict and the report's path of a finished run, else why it stopped; exit with the outcome's
    code. Messages are printed as text (click's echo, styled on a terminal), never as markup: they quote file
    names and device replies."""
    run, state, summary = outcome.run, outcome.state, outcome.summary
    code = for_run(state, summary.get("verdict"))
    if state == "done":
        coverage = 100 * (summary.get("coverage") or 0)
        verdict = f"verdict: {str(summary.get('verdict')).upper()}  ({summary.get('n_points')} points"
        typer.secho(f"{verdict}, coverage {coverage:.2f} %)", bold=True)
        for line in verdict_reasons_lines(run.results_dir / "report.json"):
            typer.echo(line)
        typer.echo(f"report: {run.results_dir / 'report.html'}")
    elif code is ExitCode.PAUSED:
        typer.secho(f"paused: {outcome.message}", fg="yellow")
        typer.echo(f"fix the cause, then: cell resume {run.path}")
    else:
        typer.secho(f"{state}: {outcome.message}", fg="red")
        typer.echo(f"run folder: {run.path}")
    if code is not ExitCode.PASS:
        sys.exit(int(code))


def register(app: typer.Typer) -> None:
    @app.command("inspect")
    def inspect_cmd(
        recipe: Path = typer.Argument(..., help="inspection recipe YAML"),
        cell: Path = typer.Option(DEFAULT_CELL, "--cell", help="cell config YAML"),
        out: Path = typer.Option(None, "--out", help="run folder to create (default: runs/<part>-<time>)"),
        sim_actual: Path = typer.Option(
            None, "--sim-actual", help="simulation: mesh rendered as the made part"
        ),
        seed: int = typer.Option(None, "--seed", help="simulation noise seed (default: the cell's sim.seed)"),
        serial: str = typer.Option(
            None, "--serial", help="the part's serial number (a barcode reader types it)"
        ),
        operator: str = typer.Option(None, "--operator", help="who runs the inspection"),
        order: str = typer.Option(None, "--order", help="production or work order number"),
        pipelining: bool = typer.Option(True, help="decode view k while moving to view k+1"),
        record: Path = typer.Option(
            None,
            "--record",
            help="record every device call into this folder as replay fixtures, with a cell.yaml that "
            "replays them (docs/fixtures.md)",
        ),
    ) -> None:
        """Run an inspection recipe end to end; Ctrl-C pauses safely (resume with `cell resume DIR`)."""
        typer.echo(f"inspecting {recipe} on cell {cell} -> {out or 'a new run folder in ' + str(RUNS_ROOT)}")
        from cell.inspection_run import inspect
        from cell.run_data import RunIdentity

        outcome = inspect(
            recipe,
            cell,
            out,
            sim_actual,
            seed=seed,
            pipelining=pipelining,
            identity=RunIdentity(serial, operator, order),
            record=record,
            on_progress=_progress,
            say=_say,
        )
        _finish(outcome)

    @app.command("resume")
    def resume_cmd(run_dir: Path = typer.Argument(..., help="run folder of an interrupted run")) -> None:
        """Finish an interrupted or paused run from its last checkpoint, with the settings it started with."""
        typer.echo(f"resuming the run in {run_dir}")
        from cell.inspection_run import resume

        _finish(resume(run_dir, on_progress=_progress, say=_say))

    @app.command("report")
    def report_cmd(
        run_dir: Path = typer.Argument(..., help="run folder"),
        pdf: bool = typer.Option(False, "--pdf", help="also print results/report.pdf (headless Chromium)"),
        csv: bool = typer.Option(False, "--csv", help="also write results/deviations.csv (x,y,z,deviation)"),
    ) -> None:
        """Rebuild a finished run's report from its stored views (docs/report.md)."""
        typer.echo(f"rebuilding the report of {run_dir}")
        from cell.inspection_run import rebuild_report

        _finish(rebuild_report(run_dir, csv=csv, pdf=pdf))

    @app.command("demo")
    def demo_cmd(
        runs: Path = typer.Option(RUNS_ROOT, "--runs", help="runs root; each demo makes a new run folder"),
        cell: Path = typer.Option(
            DEMO_CELL,
            "--cell",
            help="cell config; default: the honest simulated world, recipes/cells/sim.yaml",
        ),
        calibrate: bool = typer.Option(
            True,
            "--calibrate/--no-calibrate",
            help="first `cell calibrate all` of CELL into RUNS/calibration-<cell> unless a valid calibration "
            "of that cell file is there, then inspect with it",
        ),
    ) -> None:
        """A full simulated inspection of the demo pillar (with its dented actual), ending in a report. By
        default in the honest simulated world (recipes/cells/sim.yaml: hand-eye, lens, projector, robot and
        placement errors the pipeline does not know), calibrated first by `cell calibrate all` (about two
        minutes, reused while the cell file is unchanged); `--cell recipes/cells/sim_ideal.yaml
        --no-calibrate` runs it in the ideal world, whose figures are a noise floor."""
        typer.echo(f"demo: the pillar on cell {cell} -> a new run folder in {runs}")
        from cell.inspection_run import demo

        _finish(demo(runs, cell, calibrate=calibrate, on_progress=_progress, say=_say))
