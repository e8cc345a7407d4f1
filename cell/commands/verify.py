"""``cell verify acceptance``: the VDI/VDE 2634 Part 2 acceptance test of the cell (one view)."""

from __future__ import annotations

import shutil
from pathlib import Path

import typer

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
) -> None:
    """Measure the ball bar (7 positions) and the plane (6 positions) in the single-view measuring volume;
    write report.html and verification.json to OUT and print PF, PS, SD and F against their MPEs."""
    from cell.config import DEFAULT_CELL, load_cell_config
    from cell.devices import build_artefact_stage, build_devices
    from cell.errors import ConfigError
    from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate
    from cell.verification.procedure import run_acceptance
    from cell.verification.report import write_html, write_json

    cfg_path = cell or DEFAULT_CELL
    cfg = load_cell_config(cfg_path)
    cert_path = certificate or cfg.verification.certificate or DEFAULT_CERTIFICATE
    if not Path(cert_path).is_absolute() and certificate is None and cfg.verification.certificate is not None:
        cert_path = Path(cfg_path).resolve().parent / cert_path
    cert = load_certificate(cert_path)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ConfigError("output folder exists and is not empty; choose another --out", path=str(out))
    (out / "inputs").mkdir(parents=True, exist_ok=True)
    shutil.copy2(cfg_path, out / "inputs" / "cell.yaml")
    shutil.copy2(cert_path, out / "inputs" / "certificate.yaml")

    devices = build_devices(cfg)
    stage = build_artefact_stage(devices, cert)
    result, _ = run_acceptance(
        cfg, devices, stage, cert, progress=lambda k, n, label: typer.echo(f"position {k + 1}/{n}: {label}")
    )
    note = (
        f"Simulated cell ({cfg_path}): its world: section says how the simulated world differs from the "
        "config; where it is 'ideal' these figures are a noise floor."
        if devices.sim is not None
        else f"Cell {cfg_path}."
    )
    write_json(out / "verification.json", result, cert, note)
    write_html(out / "report.html", result, cert, note)
    for k, v in result.figures_mm.items():
        shown = "not measured" if v is None else f"{v * 1000:+.1f} um"
        mpe = result.mpe_mm[k] * 1000
        status = {True: "pass", False: "FAIL", None: "-"}[result.passed[k]]
        typer.echo(f"{k:>2}: {shown:>14}  (MPE {mpe:.1f} um)  {status}")
    typer.echo(f"verdict: {result.verdict} -> {out / 'report.html'}")


def register(app: typer.Typer) -> None:
    app.add_typer(verify_app, name="verify")
