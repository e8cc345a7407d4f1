"""The life of an inspection run folder: start it (every input checked, then copied into the folder), execute
or resume it under the folder's lock with the settings it started with, rebuild its report; and the demo.
``cell inspect``, ``cell resume``, ``cell report`` and ``cell demo`` are these calls.

A run reads only the copies in its ``inputs/`` folder once it has started, so a resume finishes it even if the
original recipe, CAD or cell config changed or moved meanwhile. The inspection itself (plan, views, judging)
is the job of :mod:`cell.inspection`, run by :mod:`cell.controller`; both load on demand.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from cell.config import CellConfig, PartConfig, Recipe, load_cell_config, load_recipe, read_yaml, validate
from cell.defaults import DEMO_CELL as DEMO_CELL  # the honest world: it differs from the config
from cell.errors import ConfigError
from cell.run_data import Checkpoint, Phase, RunIdentity
from cell.runs import (
    RESUME_OR_ANOTHER,
    RUNS_ROOT,
    RunFolder,
    require_empty_output,
    write_atomic,
    write_json_atomic,
)
from cell.storage import new_folder, require_writable

if TYPE_CHECKING:
    from cell.results import ResultsStore

REPO = Path(__file__).resolve().parents[1]
DEMO_RECIPE = REPO / "recipes" / "pillar.yaml"
IDEAL_CELL = REPO / "recipes" / "cells" / "sim_ideal.yaml"  # the world equals the config: a noise floor

Say = Callable[[str], None]


@dataclass
class RunOutcome:
    """How an execution ended: the run folder, the controller's last state (``done``, ``paused``, ...) and
    message, and the run's summary (verdict, points, coverage, deviation) from its checkpoint."""

    run: RunFolder
    state: str
    message: str
    summary: dict[str, Any]


def start_run(
    recipe_path: Path,
    cell_path: Path,
    out: Path | None = None,
    sim_actual: Path | None = None,
    *,
    seed: int | None = None,
    pipelining: bool = True,
    identity: RunIdentity = RunIdentity(),
) -> RunFolder:
    """Validate every input, then create the run folder ``out`` (default ``runs/<part>[-<serial>]-<time>``)
    and copy the inputs into it (nothing before that). The run's settings (seed, pipelining) are recorded so
    that a resume continues it as it started; its identity (serial, operator, order) for the report and the
    results database."""
    from cell.calibration import active_sensor_config, active_triangulator
    from cell.mesh import load_part_W

    cfg = load_cell_config(cell_path)
    recipe = load_recipe(recipe_path)
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
    final = out if out else RUNS_ROOT / RunFolder.new_name(part, identity.serial or "")
    from cell.verification.history import inspection_block

    blocked = inspection_block(final.parent, cfg.name, cfg.verification.block_inspections, cfg)
    if blocked:
        raise ConfigError(blocked, path=str(cell_path))
    holder = RunFolder(final).lock_holder() if final.is_dir() else None
    if holder is not None and RunFolder(final).holder_is_live(holder):
        raise ConfigError(
            f"run folder in use by PID {holder.get('pid')} on host {holder.get('host')} "
            f"({holder.get('command')}); choose another --out",
            path=str(final),
        )
    require_empty_output(final, then=RESUME_OR_ANOTHER)
    # the folder appears under its name only once every input is copied: a run killed before that never
    # started, and leaves nothing that a resume could mistake for a run
    partial = final.parent / f".{final.name}.partial-{os.getpid()}"
    with new_folder(partial, shown=final):  # the disk filling up meanwhile: refused, nothing left
        run = RunFolder.create(final.parent, part, name=partial.name)
        run.acquire_lock("cell inspect")  # held from the start: the folder appears under its name locked
        manifest: dict[str, Any] = {
            "recipe": run.copy_input(recipe_path, "recipe.yaml").name,
            "cell_as_given": run.copy_input(cell_path, "cell.original.yaml").name,
            "cell": _copy_cell_with_calibration(run, cell_path, cfg),
            "settings": {"seed": seed, "pipelining": pipelining},
            "identity": identity.to_json(),
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
        run.log("run_created", part=part, **manifest["sources"], **identity.to_json())
    if final.exists():
        final.rmdir()  # empty (checked above)
    os.replace(run.path, final)
    return RunFolder.open(final)


def _copy_cell_with_calibration(run: RunFolder, cell_path: Path, cfg: CellConfig) -> str:
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


def uncalibrated_warning(
    cell: Path, cfg: CellConfig, roots: Sequence[Path] = (RUNS_ROOT,), shown: str | Path | None = None
) -> str | None:
    """One line when the cell config ``cfg`` (read from the file ``cell``, named ``shown``, default ``cell``)
    names no calibration file: the run measures with the config's nominal geometry, which on a real cell (or
    the honest simulated one) usually ends INCOMPLETE; with how to calibrate, or the calibration of this very
    file that `cell calibrate all` made in a ``calibration-*`` folder under one of ``roots`` (as `cell demo`
    finds it: :func:`cell.calibration.routines.valid_calibration`). None when a calibration is named. (Said
    in an ideal simulated world too: what the simulator renders is not the pipeline's to know,
    tests/test_world_isolation.py.)"""
    if any(v is not None for v in cfg.calibration.model_dump().values()):
        return None
    from cell.calibration.routines import valid_calibration

    shown = shown or cell
    folders = sorted({f.resolve() for root in roots for f in Path(root).glob("calibration-*") if f.is_dir()})
    found = next((c for f in folders if (c := valid_calibration(cell, f)) is not None), None)
    then = (
        f"a calibration of this cell is in {found.parent}: inspect with --cell {found}"
        if found is not None
        else f"calibrate it with `cell calibrate all --cell {shown} --out DIR`, then inspect with --cell "
        "DIR/cell.yaml"
    )
    return (
        f"warning: the cell config {shown} names no calibration: this run measures with its nominal "
        f"geometry, and an uncalibrated cell usually ends INCOMPLETE; {then}"
    )


def _warn_if_uncalibrated(run: RunFolder, say: Say) -> None:
    """Say :func:`uncalibrated_warning` of the cell config a run was started with (its copy in inputs/, the
    file as given identifying its calibrations), naming the file as given."""
    inputs = run.path / "inputs"
    manifest = json.loads((inputs / "manifest.json").read_text())
    given = inputs / manifest.get("cell_as_given", manifest["cell"])
    cfg = load_cell_config(inputs / manifest["cell"])
    shown = manifest.get("sources", {}).get("cell") or given
    warning = uncalibrated_warning(given, cfg, (RUNS_ROOT, run.path.parent), shown)
    if warning:
        say(warning)


def open_inspection_run(run_dir: Path) -> RunFolder:
    """An inspection's run folder; a calibration or verification folder is resumed by its own command."""
    run = RunFolder.open(run_dir)
    if run.kind != "inspection":
        raise ConfigError(
            "not an inspection run (no inputs/manifest.json); a calibration or verification run resumes by "
            "running its `cell calibrate ...` or `cell verify ...` command again with this folder as --out",
            path=str(run_dir),
        )
    return run


def run_identity(run: RunFolder) -> RunIdentity:
    """The serial, operator and order a run was started with (none for runs older than the field)."""
    manifest = json.loads((run.path / "inputs" / "manifest.json").read_text())
    return RunIdentity.from_json(manifest.get("identity"))


def run_settings(run: RunFolder) -> dict[str, Any]:
    """The settings a run was started with (seed, pipelining)."""
    manifest = json.loads((run.path / "inputs" / "manifest.json").read_text())
    return manifest.get("settings", {"seed": None, "pipelining": True})


def load_run_inputs(run: RunFolder) -> tuple[Recipe, CellConfig, Path | None]:
    """The recipe, the cell config and the simulated actual part (or None) as copied into the run, with the
    part paths pointing at the copies."""
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


def execute_run(
    run: RunFolder,
    *,
    resume: bool,
    record: Path | None = None,
    on_progress: Callable[[Any], None] | None = None,
    say: Say = print,
) -> RunOutcome:
    """Run (or resume) a run folder with the settings it was started with; with ``record``, every device
    call is recorded there as replay fixtures (also when the run pauses or fails). Holds the folder's lock
    throughout: a second process on the same folder is refused with this one's PID and host.
    ``on_progress(controller)`` is called at every state change and view."""
    run.acquire_lock("cell resume" if resume else "cell inspect")
    try:
        return _execute_locked(run, resume, record, on_progress, say)
    finally:
        run.release_lock()


def _execute_locked(
    run: RunFolder, resume: bool, record: Path | None, on_progress: Callable[[Any], None] | None, say: Say
) -> RunOutcome:
    from cell.controller import ControllerSettings
    from cell.devices import build_devices, record_devices, save_recording
    from cell.inspection import LambertianInspection, inspection_controller
    from cell.mesh import load_mesh

    started = run_settings(run)
    recipe, cfg, actual_path = load_run_inputs(run)
    settings = ControllerSettings(  # the recipe's view budget and feedback iterations (initial views + k)
        pipelining=bool(started.get("pipelining", True)),
        view_budget=recipe.plan.view_budget,
        max_iterations=recipe.plan.max_iterations + 1,
    )
    T_W_P = recipe.part.T_W_P.matrix()
    nominal_W = load_mesh(recipe.part.cad).apply_transform(T_W_P)
    actual_W = load_mesh(actual_path).apply_transform(T_W_P) if actual_path else nominal_W
    devices = build_devices(
        cfg, part_W=actual_W, part_material=recipe.part.material, seed=started.get("seed")
    )
    if record is not None:
        devices = record_devices(devices)
    job = LambertianInspection(recipe, cfg, nominal_W)
    ctl = inspection_controller(devices, job, run, settings, on_progress=on_progress)
    from cell.results import open_results

    results = open_results(cfg, run.path.parent)
    results.record_or_defer(run.path)  # "running"; whatever the database does, the run goes on
    try:
        state = ctl.execute(resume=resume)
    finally:
        if record is not None:
            saved = save_recording(devices, record, cfg.model_dump(mode="json"))
            say(f"device traffic recorded: replay with --cell {saved / 'cell.yaml'}")
    if state == "done":  # the cell's retention for this verdict may keep no raw images past the run
        from cell.retention import apply_at_finish

        pruned = apply_at_finish(run, cfg.retention)
        if pruned is not None:
            say(f"raw view images removed ({pruned.freed_bytes / 1e6:.1f} MB): {pruned.reason}")
        from cell.inspection_views import remove_planes

        remove_planes(run)  # a cache for a resume, recomputed from the stored points when read again
    summary = Checkpoint.from_json(run.load_checkpoint()).summary or {}
    _record_results(run, results, say)
    return RunOutcome(run, state, ctl.message, summary)


def _record_results(run: RunFolder, results: ResultsStore, say: Say) -> None:
    """Record the run in the results database; when it cannot be, journal why and leave the folder's
    pending marker for the next `cell history --sync` (the run's own files are complete either way)."""
    reason = results.record_or_defer(run.path)
    results.close()
    if reason is None:
        run.log("results_recorded", database=results.where)
        return
    run.log("results_not_recorded", database=results.where, reason=reason)
    say(f"results not recorded in the database yet: {reason}")


def inspect(
    recipe: Path,
    cell: Path,
    out: Path | None = None,
    sim_actual: Path | None = None,
    *,
    seed: int | None = None,
    pipelining: bool = True,
    identity: RunIdentity = RunIdentity(),
    record: Path | None = None,
    on_progress: Callable[[Any], None] | None = None,
    say: Say = print,
) -> RunOutcome:
    """Start a run of ``recipe`` on ``cell`` (see :func:`start_run`) and execute it."""
    if record is not None:
        require_empty_output(record, field="--record")
    run = start_run(recipe, cell, out, sim_actual, seed=seed, pipelining=pipelining, identity=identity)
    _warn_if_uncalibrated(run, say)
    return execute_run(run, resume=False, record=record, on_progress=on_progress, say=say)


def resume(
    run_dir: Path, *, on_progress: Callable[[Any], None] | None = None, say: Say = print
) -> RunOutcome:
    """Finish an interrupted or paused inspection run from its last checkpoint; a finished one is refused."""
    from cell.controller import stopped_state

    run = open_inspection_run(run_dir)
    if Checkpoint.from_json(run.load_checkpoint()).phase is Phase.DONE:
        raise ConfigError("this run is already done; `cell report` rebuilds its report", path=str(run_dir))
    if stopped_state(run) == "aborted":
        raise ConfigError("this run was aborted; start a new run of the part", path=str(run_dir))
    _warn_if_uncalibrated(run, say)
    return execute_run(run, resume=True, on_progress=on_progress, say=say)


def abort_run(run_dir: Path, reason: str) -> str:
    """Abort an inspection run that no process executes (paused, or stopped by a fault or a kill) through
    the controller's state machine (:func:`cell.controller.abort_stopped`), under the run's lock: a run that a
    live process executes is refused with that process named (pause it first); a finished or an aborted one is
    refused by the machine. ``reason`` (who aborted it, and where) goes into the journal; returns the new
    state, ``aborted``. The run's files stay as they are: nothing measured is deleted."""
    from cell.controller import abort_stopped

    run = open_inspection_run(run_dir)
    run.acquire_lock("abort")
    try:
        state = abort_stopped(run, reason)
    finally:
        run.release_lock()
    from cell.results import open_results

    _, cfg, _ = load_run_inputs(run)
    _record_results(run, open_results(cfg, run.path.parent), lambda _: None)
    return state


def rebuild_report(run_dir: Path, *, csv: bool = False, pdf: bool = False) -> RunOutcome:
    """Rebuild the report of a run that reached reporting from its stored views (journalled); with ``csv``
    also deviations.csv, with ``pdf`` also report.pdf (headless Chromium). An aborted run has no report
    (its verdict was never published) and is refused as such; a paused or faulted one is pointed to `cell
    resume`."""
    from cell.controller import stopped_state

    run = open_inspection_run(run_dir)
    checkpoint = Checkpoint.from_json(run.load_checkpoint())
    if stopped_state(run) == "aborted":
        raise ConfigError(
            "this run was aborted before its verdict, so it has no report (and cannot be resumed); start a "
            "new run of the part",
            path=str(run_dir),
        )
    if checkpoint.phase not in (Phase.REPORTING, Phase.RENDERING, Phase.DONE):
        raise ConfigError("the run has not reached reporting; `cell resume` it first", path=str(run_dir))
    require_writable(run.results_dir, field=None)  # a read-only or full results folder: refused first
    if pdf:
        from cell.chromium import require_chromium

        require_chromium()  # before the rebuild, not after it
    from cell.inspection import LambertianInspection
    from cell.mesh import load_mesh

    recipe, cfg, _ = load_run_inputs(run)
    nominal_W = load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
    job = LambertianInspection(recipe, cfg, nominal_W)
    summary = job.report(run, checkpoint.registration or {}, csv=csv)
    job.render(run)
    if pdf:
        from cell.analysis.report import print_report_pdf

        print_report_pdf(run.results_dir)
    run.log("report_rebuilt", csv=csv, pdf=pdf, **summary)
    return RunOutcome(run, "done", "", summary)


def demo(
    runs: Path,
    cell: Path = DEMO_CELL,
    *,
    calibrate: bool = True,
    on_progress: Callable[[Any], None] | None = None,
    say: Say = print,
) -> RunOutcome:
    """A simulated inspection of the demo pillar (with its dented actual) into a new folder under ``runs``;
    with ``calibrate``, on the calibration of ``cell`` in ``runs/calibration-<cell>``, made first unless a
    valid one is there (:func:`cell.calibration.routines.ensure_calibration`)."""
    recipe = load_recipe(DEMO_RECIPE)
    part = recipe.name or recipe.part.cad.stem
    if calibrate:
        from cell.calibration.routines import ensure_calibration

        cell = ensure_calibration(cell, runs / f"calibration-{cell.stem}", say=say)
    out = runs / RunFolder.new_name("demo", part)
    say(
        f"simulated inspection of {DEMO_RECIPE.relative_to(REPO)} (actual part: "
        f"{recipe.part.actual.name if recipe.part.actual else 'nominal'}) with {cell} -> {out}"
    )
    if cell.resolve() == IDEAL_CELL.resolve():
        say("ideal simulated world: the world equals the model, so the deviations are a noise floor")
    run = start_run(DEMO_RECIPE, cell, out, None)
    return execute_run(run, resume=False, on_progress=on_progress, say=say)
