"""``cell verify acceptance`` (the VDI/VDE 2634 Part 2 acceptance test of the cell, one view), ``cell verify
check`` (the short interim check, stored in the runs root's history with a drift warning) and ``cell verify
history``."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

REPO = Path(__file__).resolve().parents[2]

verify_app = typer.Typer(
    help="Acceptance test and re-verification after VDI/VDE 2634 (sphere, ball bar, plane).",
    no_args_is_help=True,
)


@verify_app.command("acceptance")
def acceptance_cmd(
    out: Path = typer.Option(..., "--out", help="run folder to write (an unfinished one is resumed)"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    certificate: Path = typer.Option(
        None, "--certificate", help="artefact certificate YAML (default: the cell's verification.certificate)"
    ),
    part: int = typer.Option(
        2, "--part", help="2: one view, ball bar and plane in 13 positions; 3: the long bar across views"
    ),
) -> None:
    """Part 2: the ball bar (7 positions) and the plane (6 positions) in the single-view measuring volume.
    Part 3: the long ball bar in 3 directions, each across 4 views of the robot-moved sensor. Runs under the
    controller (pause with Ctrl-C, run again to resume); writes report.html and verification.json to OUT and
    prints PF, PS, SD and F against their MPEs. Exit code 0 whatever the verdict (the report holds it); an
    acceptance test is a record in its folder, not part of the shift history `cell verify check` keeps."""
    from cell.verification.job import VerificationJob

    cfg_path, cfg, cert_path, cert = _load(cell, certificate)
    job = VerificationJob(cfg, cert, part=part)
    result = _run(job, out, cfg_path, cert_path)
    typer.echo(f"verdict: {result.verdict} -> {Path(out) / 'report.html'}")


def _load(cell: Path | None, certificate: Path | None):  # noqa: ANN202 - (cfg path, cfg, cert path, cert)
    from cell.config import DEFAULT_CELL, load_cell_config
    from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate

    cfg_path = cell or DEFAULT_CELL
    cfg = load_cell_config(cfg_path)
    cert_path = certificate or cfg.verification.certificate or DEFAULT_CERTIFICATE
    if certificate is None and cfg.verification.certificate is not None and not Path(cert_path).is_absolute():
        cert_path = Path(cfg_path).resolve().parent / cert_path
    return cfg_path, cfg, cert_path, load_certificate(cert_path)


def _run(job, out: Path, cfg_path: Path, cert_path: Path):  # noqa: ANN001, ANN202 - AcceptanceResult
    """Run the verification job into ``out`` under the controller, print its figures; the result."""
    from cell.calibration.routines import run_routine
    from cell.verification.procedure import AcceptanceResult

    shown: set[int] = set()

    def progress(controller) -> None:  # noqa: ANN001
        done, total = controller.views_done, controller.views_total
        if total and done not in shown:
            shown.add(done)
            typer.echo(f"view {done}/{total}")

    doc = run_routine(
        job, Path(out), cfg_path, on_progress=progress, inputs={"certificate.yaml": Path(cert_path)}
    )
    result = AcceptanceResult.from_dict(doc)
    for k, v in result.figures_mm.items():
        sign = "+" if k in ("PS", "SD") else ""
        shown_value = "not measured" if v is None else f"{v * 1000:{sign}.1f} um"
        status = {True: "pass", False: "FAIL", None: "-"}[result.passed[k]]
        mpe = f"{'+-' if sign else ''}{result.mpe_mm[k] * 1000:.1f}"
        typer.echo(f"{k:>2}: {shown_value:>14}  (MPE {mpe} um)  {status}")
    return result


@verify_app.command("check")
def check_cmd(
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    certificate: Path = typer.Option(None, "--certificate", help="artefact certificate YAML"),
    runs: Path = typer.Option(REPO / "runs", "--runs", help="runs root holding index.sqlite"),
) -> None:
    """The interim check for the start of a shift: one ball-bar and one plane position. Its figures join the
    verification history in RUNS; warns when a figure drifts toward its MPE, exits 1 when one exceeds it."""
    from cell.errors import RoutinePaused
    from cell.runs import RunFolder
    from cell.verification.history import VerificationHistory, drift_warnings
    from cell.verification.job import VerificationJob
    from cell.verification.procedure import check_positions

    cfg_path, cfg, cert_path, cert = _load(cell, certificate)
    note = "Interim check (one ball-bar and one plane position)."
    job = VerificationJob(cfg, cert, positions=check_positions(cfg, cert), note=note, interim=True)
    folder = Path(runs) / RunFolder.new_name("verify-check")
    try:
        result = _run(job, folder, cfg_path, cert_path)
    except RoutinePaused as exc:  # a check is short: start a new one rather than resume an old one
        raise RoutinePaused(
            f"interim check paused ({exc}); run `cell verify check` again for a new check"
        ) from exc
    history = VerificationHistory(runs)
    history.add(folder, "check", result)
    checks = [e for e in history.entries(cfg.name) if e.kind == "check"]
    for warning in drift_warnings(checks, result.mpe_mm, warn_fraction=cfg.verification.warn_fraction):
        typer.echo(f"WARNING: {warning}")
    typer.echo(f"check: {result.verdict} -> {folder / 'report.html'}")
    if result.verdict == "fail":
        sys.exit(1)  # typer.Exit would be swallowed by the non-standalone app (cell.cli.main)


@verify_app.command("history")
def history_cmd(
    cell: str = typer.Option(None, "--cell-name", help="only this cell (its config's name)"),
    runs: Path = typer.Option(REPO / "runs", "--runs", help="runs root holding index.sqlite"),
) -> None:
    """Every stored interim check, oldest first: PF, PS, SD, F (um) and the verdict."""
    from cell.verification.history import FIGURES, VerificationHistory

    typer.echo(f"{'time':<26}{'kind':<12}{'cell':<24}" + "".join(f"{k:>9}" for k in FIGURES) + "  verdict")
    for e in VerificationHistory(runs).entries(cell):
        values = "".join(
            f"{'-':>9}" if e.figures_mm[k] is None else f"{e.figures_mm[k] * 1000:>9.1f}" for k in FIGURES
        )
        typer.echo(f"{e.time:<26}{e.kind:<12}{e.cell:<24}{values}  {e.verdict}")


def register(app: typer.Typer) -> None:
    app.add_typer(verify_app, name="verify")
