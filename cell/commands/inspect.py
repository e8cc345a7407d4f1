"""``cell inspect``, ``cell resume``, ``cell report``, ``cell history``, ``cell diagram`` and ``cell demo``.

A run reads only the copies in its ``inputs/`` folder once it has started, so ``cell resume`` finishes it even
if the original recipe, CAD or cell config changed or moved meanwhile.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import typer
import yaml
from rich.console import Console

from cell.config import DEFAULT_CELL, PartConfig, Recipe, load_cell_config, load_recipe, read_yaml, validate
from cell.controller import Controller, ControllerSettings
from cell.errors import ConfigError
from cell.runs import RunFolder, RunIndex, write_atomic, write_json_atomic

REPO = Path(__file__).resolve().parents[2]
DEMO_RECIPE = REPO / "recipes" / "pillar.yaml"
DEMO_CELL = REPO / "recipes" / "cells" / "sim.yaml"  # the honest world: it differs from the config
IDEAL_CELL = REPO / "recipes" / "cells" / "sim_ideal.yaml"  # the world equals the config: a noise floor
console = Console()
EXIT_PAUSED = 3


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
    console.print(f"[{elapsed:6.1f} s] {ctl.state}{view}{remaining}", highlight=False)


def _start_run(
    recipe_path: Path,
    cell_path: Path,
    out: Path | None,
    sim_actual: Path | None,
    seed: int | None = None,
    pipelining: bool = True,
) -> RunFolder:
    """Validate every input, then create the run folder and copy the inputs into it (nothing before that).
    The run's settings (seed, pipelining) are recorded so that `cell resume` continues it as it started."""
    cfg = load_cell_config(cell_path)
    recipe = load_recipe(recipe_path)
    from cell.calibration import active_sensor_config, active_triangulator
    from cell.commands.plan import load_part_W

    part_W = load_part_W(recipe, recipe_path, cfg)  # refuses a part that is invalid or does not fit the cell
    if recipe.alignment.datums:  # refuses datums off the part or not fixing it
        from cell.analysis.alignment import check_datums
        from cell.geometry import invert

        check_datums(
            recipe.alignment.datums,
            part_W.apply_transform(invert(recipe.part.T_W_P.matrix())),
            str(recipe_path),
        )
    active_sensor_config(cfg)  # refuses calibration files of the wrong kind or for another camera
    active_triangulator(cfg)
    actual = sim_actual or recipe.part.actual
    if sim_actual is not None:
        from cell.mesh import load_mesh

        load_mesh(sim_actual, what="simulated actual part")
    part = recipe.name or recipe.part.cad.stem
    final = out if out else REPO / "runs" / f"{part}-{time.strftime('%Y%m%dT%H%M%S')}"
    from cell.verification.history import inspection_block

    blocked = inspection_block(final.parent, cfg.name, cfg.verification.block_inspections)
    if blocked:
        raise ConfigError(blocked, path=str(cell_path))
    holder = RunFolder(final).lock_holder() if final.is_dir() else None
    if holder is not None and RunFolder(final).holder_is_live(holder):
        raise ConfigError(
            f"run folder in use by PID {holder.get('pid')} on host {holder.get('host')} "
            f"({holder.get('command')}); choose another --out",
            path=str(final),
        )
    if final.exists() and any(final.iterdir()):
        raise ConfigError(
            "run folder exists and is not empty; choose another --out or `cell resume` it", path=str(final)
        )
    # the folder appears under its name only once every input is copied: a run killed before that never
    # started, and leaves nothing that `cell resume` could mistake for a run
    run = RunFolder.create(final.parent, part, name=f".{final.name}.partial-{os.getpid()}")
    run.acquire_lock("cell inspect")  # held from the start: the folder appears under its name locked
    manifest: dict[str, Any] = {
        "recipe": run.copy_input(recipe_path, "recipe.yaml").name,
        "cell_as_given": run.copy_input(cell_path, "cell.original.yaml").name,
        "cell": _copy_cell_with_calibration(run, cell_path, cfg),
        "settings": {"seed": seed, "pipelining": pipelining},
        "cad": run.copy_input(recipe.part.cad, "nominal" + recipe.part.cad.suffix).name,
        "actual": run.copy_input(actual, "actual" + Path(actual).suffix).name if actual else None,
        "sources": {
            "recipe": str(recipe_path),
            "cell": str(cell_path),
            "cad": str(recipe.part.cad),
            "actual": str(actual) if actual else None,
        },
    }
    write_json_atomic(run.path / "inputs" / "manifest.json", manifest)
    run.log("run_created", part=part, **manifest["sources"])
    if final.exists():
        final.rmdir()  # empty (checked above)
    os.replace(run.path, final)
    return RunFolder.open(final)


def _copy_cell_with_calibration(run: RunFolder, cell_path: Path, cfg: Any) -> str:
    """Copy the cell config with its calibration files into inputs/, the copy pointing at the copies: a
    calibration redone or moved after the run started cannot change how the run is finished."""
    data = read_yaml(cell_path)
    target = run.path / "inputs" / "calibration"
    for field, source in cfg.calibration.model_dump().items():
        if source is None:
            continue
        source = Path(source)
        dest = target / field / source.name
        dest.parent.mkdir(parents=True, exist_ok=True)
        if source.is_dir():
            shutil.copytree(source, dest)
        else:
            shutil.copy2(source, dest)
            arrays = source.with_suffix(".npz")  # a calibration's YAML names its arrays file beside it
            if arrays.is_file():
                shutil.copy2(arrays, dest.with_suffix(".npz"))
        data.setdefault("calibration", {})[field] = str(dest.relative_to(run.path / "inputs"))
    write_atomic(run.path / "inputs" / "cell.yaml", yaml.safe_dump(data, sort_keys=False).encode())
    return "cell.yaml"


def _inspection_run(run_dir: Path) -> RunFolder:
    """An inspection's run folder; a calibration or verification folder is resumed by its own command."""
    run = RunFolder.open(run_dir)
    if run.kind != "inspection":
        raise ConfigError(
            "not an inspection run (no inputs/manifest.json); a calibration or verification run resumes by "
            "running its `cell calibrate ...` or `cell verify ...` command again with this folder as --out",
            path=str(run_dir),
        )
    return run


def run_settings(run: RunFolder) -> dict[str, Any]:
    """The settings a run was started with (seed, pipelining)."""
    manifest = json.loads((run.path / "inputs" / "manifest.json").read_text())
    return manifest.get("settings", {"seed": None, "pipelining": True})


def _load_run_inputs(run: RunFolder) -> tuple[Recipe, Any, Path | None]:
    """The recipe and cell config as copied into the run, with the part paths pointing at the copies."""
    inputs = run.path / "inputs"
    manifest = json.loads((inputs / "manifest.json").read_text())
    recipe_file = inputs / manifest["recipe"]
    data = read_yaml(recipe_file)
    data.setdefault("part", {})
    data["part"] = {**data["part"], "cad": str(inputs / manifest["cad"]), "actual": None}
    recipe = validate(Recipe, data, recipe_file)
    recipe.part = PartConfig.model_validate({**recipe.part.model_dump(), "cad": inputs / manifest["cad"]})
    cfg = load_cell_config(inputs / manifest["cell"])
    actual = inputs / manifest["actual"] if manifest.get("actual") else None
    return recipe, cfg, actual


def _execute(run: RunFolder, *, resume: bool, record: Path | None = None) -> str:
    """Run (or resume) a run folder with the settings it was started with; with ``record``, every device
    call is recorded there as replay fixtures (also when the run pauses or fails). Holds the folder's lock
    throughout: a second process on the same folder is refused with this one's PID and host."""
    run.acquire_lock("cell resume" if resume else "cell inspect")
    try:
        return _execute_locked(run, resume=resume, record=record)
    finally:
        run.release_lock()


def _execute_locked(run: RunFolder, *, resume: bool, record: Path | None) -> str:
    started = run_settings(run)
    seed = started.get("seed")
    from cell.devices import build_devices
    from cell.inspection import LambertianInspection, inspection_controller
    from cell.mesh import load_mesh

    recipe, cfg, actual_path = _load_run_inputs(run)
    settings = ControllerSettings(  # the recipe's view budget and feedback iterations (initial views + k)
        pipelining=bool(started.get("pipelining", True)),
        view_budget=recipe.plan.view_budget,
        max_iterations=recipe.plan.max_iterations + 1,
    )
    T_W_P = recipe.part.T_W_P.matrix()
    nominal_W = load_mesh(recipe.part.cad).apply_transform(T_W_P)
    actual_W = load_mesh(actual_path).apply_transform(T_W_P) if actual_path else nominal_W
    devices = build_devices(cfg, part_W=actual_W, part_material=recipe.part.material, seed=seed)
    if record is not None:
        from drivers.recording import record_bundle

        devices = record_bundle(devices)
    job = LambertianInspection(recipe, cfg, nominal_W)
    ctl = inspection_controller(devices, job, run, settings, on_progress=_progress)
    index = RunIndex(run.path.parent)
    index.upsert(run.path, job.part_name, "running")
    try:
        state = ctl.execute(resume=resume)
    finally:
        if record is not None:
            from drivers.recording import save_bundle

            saved = save_bundle(devices, record, cfg.model_dump(mode="json"))
            console.print(f"device traffic recorded: replay with --cell {saved / 'cell.yaml'}")
    summary = (run.load_checkpoint() or {}).get("summary", {})
    dev = summary.get("deviation") or {}
    index.upsert(
        run.path,
        job.part_name,
        state,
        verdict=summary.get("verdict"),
        n_points=summary.get("n_points"),
        coverage=summary.get("coverage"),
        dev_min=dev.get("min_mm"),
        dev_max=dev.get("max_mm"),
    )
    _finish_message(run, state, ctl.message, summary)
    return state


def _finish_message(run: RunFolder, state: str, message: str, summary: dict[str, Any]) -> None:
    if state == "done":
        console.print(
            f"[bold]verdict: {str(summary.get('verdict')).upper()}[/]  "
            f"({summary.get('n_points')} points, coverage {100 * (summary.get('coverage') or 0):.2f} %)"
        )
        console.print(f"report: {run.results_dir / 'report.html'}")
        return
    if state == "paused":
        console.print(f"[yellow]paused[/]: {message}\nfix the cause, then: cell resume {run.path}")
        sys.exit(EXIT_PAUSED)
    console.print(f"[red]{state}[/]: {message}\nrun folder: {run.path}")
    sys.exit(1)


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
        pipelining: bool = typer.Option(True, help="decode view k while moving to view k+1"),
        record: Path = typer.Option(
            None,
            "--record",
            help="record every device call into this folder as replay fixtures, with a cell.yaml that "
            "replays them (docs/fixtures.md)",
        ),
    ) -> None:
        """Run an inspection recipe end to end; Ctrl-C pauses safely (resume with `cell resume DIR`)."""
        if record is not None and record.exists() and any(record.iterdir()):
            raise ConfigError("recording folder exists and is not empty; choose another", path=str(record))
        run = _start_run(recipe, cell, out, sim_actual, seed=seed, pipelining=pipelining)
        _execute(run, resume=False, record=record)

    @app.command("resume")
    def resume_cmd(run_dir: Path = typer.Argument(..., help="run folder of an interrupted run")) -> None:
        """Finish an interrupted or paused run from its last checkpoint, with the settings it started with."""
        run = _inspection_run(run_dir)
        if (run.load_checkpoint() or {}).get("phase") == "done":
            raise ConfigError(
                "this run is already done; `cell report` rebuilds its report", path=str(run_dir)
            )
        _execute(run, resume=True)

    @app.command("report")
    def report_cmd(run_dir: Path = typer.Argument(..., help="run folder")) -> None:
        """Rebuild a finished run's report from its stored views."""
        from cell.inspection import LambertianInspection
        from cell.mesh import load_mesh

        run = _inspection_run(run_dir)
        checkpoint = run.load_checkpoint() or {}
        if checkpoint.get("phase") not in ("reporting", "done"):
            raise ConfigError("the run has not reached reporting; `cell resume` it first", path=str(run_dir))
        recipe, cfg, _ = _load_run_inputs(run)
        nominal_W = load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
        summary = LambertianInspection(recipe, cfg, nominal_W).report(run, checkpoint.get("registration", {}))
        run.log("report_rebuilt", **summary)
        _finish_message(run, "done", "", summary)

    @app.command("history")
    def history_cmd(
        part: str = typer.Argument(None, help="part name (default: all parts)"),
        runs: Path = typer.Option(REPO / "runs", "--runs", help="runs root holding index.sqlite"),
    ) -> None:
        """List the runs of a part: time, status, verdict and key figures."""
        from rich.table import Table

        rows = RunIndex(runs).history(part)
        table = Table(title=f"runs of {part or 'all parts'} in {runs}")
        for column in (
            "started",
            "part",
            "status",
            "verdict",
            "points",
            "coverage",
            "dev min",
            "dev max",
            "folder",
        ):
            table.add_column(column)
        for r in rows:
            fmt = lambda v, f="{:.3f}": "" if v is None else f.format(v)  # noqa: E731
            table.add_row(
                r["started"],
                r["part"],
                r["status"],
                r["verdict"] or "",
                fmt(r["n_points"], "{}"),
                fmt(r["coverage"]),
                fmt(r["dev_min"]),
                fmt(r["dev_max"]),
                r["folder"],
            )
        console.print(table)

    @app.command("demo")
    def demo_cmd(
        runs: Path = typer.Option(
            REPO / "runs", "--runs", help="runs root; each demo makes a new run folder"
        ),
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
        recipe = load_recipe(DEMO_RECIPE)
        part = recipe.name or recipe.part.cad.stem
        if calibrate:
            from cell.calibration.routines import ensure_calibration

            cell = ensure_calibration(
                cell, runs / f"calibration-{cell.stem}", say=lambda m: console.print(m, highlight=False)
            )
        out = runs / f"demo-{part}-{time.strftime('%Y%m%d-%H%M%S')}"
        console.print(
            f"simulated inspection of {DEMO_RECIPE.relative_to(REPO)} (actual part: "
            f"{recipe.part.actual.name if recipe.part.actual else 'nominal'}) with {cell} -> {out}",
            highlight=False,
        )
        if cell.resolve() == IDEAL_CELL.resolve():
            console.print(
                "ideal simulated world: the world equals the model, so the deviations are a noise floor",
                highlight=False,
            )
        run = _start_run(DEMO_RECIPE, cell, out, None)
        _execute(run, resume=False)
