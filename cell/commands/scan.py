"""``cell scan``: one structured-light scan of a mesh in the simulated cell, from one pose."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from cell.errors import ConfigError

MODELS = ("pinhole", "reference")


def _parse_pose(text: str):  # noqa: ANN202 - returns a 4x4 pose or None for auto
    from cell.geometry import pose_from_xyz_rotvec

    if text == "auto":
        return None
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 6:
        raise ConfigError(
            f"--pose '{text}': give 'auto' or six numbers x,y,z,rx,ry,rz (camera pose T_W_C: "
            "mm and a rotation vector in rad)",
            field="--pose",
        )
    return pose_from_xyz_rotvec(values[:3], values[3:])


def scan_cmd(
    out: Path = typer.Option(..., "--out", help="output folder (created)"),
    cell: Path = typer.Option(None, "--cell", help="cell config YAML (default: recipes/cells/sim.yaml)"),
    part: Path = typer.Option(
        None, "--part", help="part mesh in world coordinates, mm (default: empty table)"
    ),
    pose: str = typer.Option(
        "auto", "--pose", help="'auto' or x,y,z,rx,ry,rz of the camera frame in {W} (mm, rotation vector rad)"
    ),
    codec: str = typer.Option("gcls", "--codec", help="gcls or gcps"),
    model: str = typer.Option("pinhole", "--model", help="triangulation: pinhole or reference (eq 2.8)"),
    seed: int = typer.Option(None, "--seed", help="noise seed (default: the cell's sim.seed)"),
    source: Path = typer.Option(
        None, "--from", help="capture folder (docs/capture-folders.md): scan its poses"
    ),
) -> None:
    """Scan MESH from one pose; write cloud.ply (world mm), masks.png and scan.json to OUT."""
    from cell.config import DEFAULT_CELL, load_cell_config
    from cell.sensing.sim_scan import run_sim_scan

    if source is not None:  # images captured elsewhere, measured with the cell's active calibration
        from cell.calibration.offline import write_folder_scan

        summary = write_folder_scan(load_cell_config(cell or DEFAULT_CELL), source, Path(out))
        (Path(out) / "scan.json").write_text(json.dumps(summary, indent=2))
        return typer.echo(f"{len(summary['poses'])} poses -> {out}")

    if codec not in ("gcls", "gcps"):
        raise ConfigError(f"--codec: unknown codec '{codec}'; use gcls or gcps", field="--codec")
    if model not in MODELS:
        raise ConfigError(f"--model: unknown model '{model}'; use {' or '.join(MODELS)}", field="--model")
    cfg_path = cell or DEFAULT_CELL
    cfg = load_cell_config(cfg_path)
    t0 = time.perf_counter()
    summary = run_sim_scan(cfg, part, _parse_pose(pose), codec, model, Path(out), seed=seed)
    summary["cell_config"] = str(cfg_path)
    summary["timings_s"]["total"] = time.perf_counter() - t0
    (Path(out) / "scan.json").write_text(json.dumps(summary, indent=2))
    c = summary["counts"]
    counts = ", ".join(f"{k} {v}" for k, v in c.items() if k != "valid")
    typer.echo(f"{c['valid']} points -> {Path(out) / 'cloud.ply'} ({counts})")


def register(app: typer.Typer) -> None:
    app.command("scan")(scan_cmd)
