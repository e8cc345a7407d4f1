"""``cell verify acceptance`` (the VDI/VDE 2634 Part 2 acceptance test of the cell, one view), ``cell verify
check`` (the short interim check, stored in the runs root's history with a drift warning) and ``cell verify
history``."""

from __future__ import annotations

import shutil
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
    out: Path = typer.Option(..., "--out", help="output folder (created; must be empty)"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    certificate: Path = typer.Option(
        None, "--certificate", help="artefact certificate YAML (default: the cell's verification.certificate)"
    ),
    part: int = typer.Option(
        2, "--part", help="2: one view, ball bar and plane in 13 positions; 3: the long bar across views"
    ),
) -> None:
    """Part 2: the ball bar (7 positions) and the plane (6 positions) in the single-view measuring volume.
    Part 3: the long ball bar in 3 directions, each across 4 views of the robot-moved sensor. Writes
    report.html and verification.json to OUT and prints PF, PS, SD and F against their MPEs."""
    from cell.errors import ConfigError
    from cell.verification.report import write_html, write_json

    if part not in (2, 3):
        raise ConfigError(f"--part {part}: give 2 (single view) or 3 (multi-view)", field="--part")
    cfg_path, cfg, cert_path, cert = _load(cell, certificate)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ConfigError("output folder exists and is not empty; choose another --out", path=str(out))
    (out / "inputs").mkdir(parents=True, exist_ok=True)
    shutil.copy2(cfg_path, out / "inputs" / "cell.yaml")
    shutil.copy2(cert_path, out / "inputs" / "certificate.yaml")

    result = _measure(cfg, cert, positions=None, multiview=part == 3)
    note = _note(cfg_path, result)
    write_json(out / "verification.json", result, cert, note)
    write_html(out / "report.html", result, cert, note)
    _print(result)
    typer.echo(f"verdict: {result.verdict} -> {out / 'report.html'}")


def _load(cell: Path | None, certificate: Path | None):  # noqa: ANN202 - (cfg path, cfg, cert path, cert)
    from cell.config import DEFAULT_CELL, load_cell_config
    from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate

    cfg_path = cell or DEFAULT_CELL
    cfg = load_cell_config(cfg_path)
    cert_path = certificate or cfg.verification.certificate or DEFAULT_CERTIFICATE
    if certificate is None and cfg.verification.certificate is not None and not Path(cert_path).is_absolute():
        cert_path = Path(cfg_path).resolve().parent / cert_path
    return cfg_path, cfg, cert_path, load_certificate(cert_path)


def _measure(cfg, cert, positions, multiview: bool = False):  # noqa: ANN001, ANN202 - AcceptanceResult
    from cell.devices import build_artefact_stage, build_devices
    from cell.verification.multiview import run_multiview
    from cell.verification.procedure import run_acceptance

    devices = build_devices(cfg)
    stage = build_artefact_stage(devices, cert)

    def progress(k: int, n: int, label: str) -> None:
        typer.echo(f"position {k + 1}/{n}: {label}")

    if multiview:
        result, _ = run_multiview(cfg, devices, stage, cert, progress=progress)
    else:
        result, _ = run_acceptance(cfg, devices, stage, cert, positions=positions, progress=progress)
    return result


def _note(cfg_path: Path, result) -> str:  # noqa: ANN001
    if result.simulated:
        return (
            f"Simulated cell ({cfg_path}): its world: section says how the simulated world differs from the "
            "config; where it is 'ideal' these figures are a noise floor."
        )
    return f"Cell {cfg_path}."


def _print(result) -> None:  # noqa: ANN001
    for k, v in result.figures_mm.items():
        sign = "+" if k in ("PS", "SD") else ""
        shown = "not measured" if v is None else f"{v * 1000:{sign}.1f} um"
        mpe = result.mpe_mm[k] * 1000
        status = {True: "pass", False: "FAIL", None: "-"}[result.passed[k]]
        typer.echo(f"{k:>2}: {shown:>14}  (MPE {mpe:.1f} um)  {status}")


@verify_app.command("check")
def check_cmd(
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    certificate: Path = typer.Option(None, "--certificate", help="artefact certificate YAML"),
    runs: Path = typer.Option(REPO / "runs", "--runs", help="runs root holding index.sqlite"),
) -> None:
    """The interim check for the start of a shift: one ball-bar and one plane position. Its figures join the
    verification history in RUNS; warns when a figure drifts toward its MPE, exits 1 when one exceeds it."""
    from cell.runs import RunFolder
    from cell.verification.history import VerificationHistory, drift_warnings
    from cell.verification.procedure import check_positions
    from cell.verification.report import write_html, write_json

    cfg_path, cfg, cert_path, cert = _load(cell, certificate)
    folder = RunFolder.create(runs, "verify-check")
    shutil.copy2(cfg_path, folder.path / "inputs" / "cell.yaml")
    shutil.copy2(cert_path, folder.path / "inputs" / "certificate.yaml")
    result = _measure(cfg, cert, positions=check_positions(cfg, cert))
    note = "Interim check (one ball-bar and one plane position). " + _note(cfg_path, result)
    write_json(folder.results_dir / "verification.json", result, cert, note)
    write_html(folder.results_dir / "report.html", result, cert, note)
    history = VerificationHistory(runs)
    history.add(folder.path, "check", result)
    _print(result)
    checks = [e for e in history.entries(cfg.name) if e.kind == "check"]
    for warning in drift_warnings(checks, result.mpe_mm, warn_fraction=cfg.verification.warn_fraction):
        typer.echo(f"WARNING: {warning}")
    typer.echo(f"check: {result.verdict} -> {folder.path}")
    if result.verdict == "fail":
        sys.exit(1)  # typer.Exit would be swallowed by the non-standalone app (cell.cli.main)


@verify_app.command("history")
def history_cmd(
    cell: str = typer.Option(None, "--cell-name", help="only this cell (its config's name)"),
    runs: Path = typer.Option(REPO / "runs", "--runs", help="runs root holding index.sqlite"),
) -> None:
    """Every stored acceptance test and check, oldest first: PF, PS, SD, F (um) and the verdict."""
    from cell.verification.history import FIGURES, VerificationHistory

    typer.echo(f"{'time':<26}{'kind':<8}{'cell':<18}" + "".join(f"{k:>9}" for k in FIGURES) + "  verdict")
    for e in VerificationHistory(runs).entries(cell):
        values = "".join(
            f"{'-':>9}" if e.figures_mm[k] is None else f"{e.figures_mm[k] * 1000:>9.1f}" for k in FIGURES
        )
        typer.echo(f"{e.time:<26}{e.kind:<8}{e.cell[:17]:<18}{values}  {e.verdict}")


def register(app: typer.Typer) -> None:
    app.add_typer(verify_app, name="verify")
