"""The runner that puts one calibration routine under the controller (:func:`run_routine`), the hand-eye
and validation entry points of ``cell calibrate``, and ``calibrate_all`` that chains the routines into one
calibration folder (reused while the cell config and its inputs are unchanged)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cell.calibration.handeye_routines import HandEyeBoardJob, HandEyeIcpJob, KinematicsJob
from cell.calibration.procedures import (
    GAUGE_CERTIFICATE,
    CalibrationJob,
    JointMotion,
)
from cell.calibration.sensor_routines import IntrinsicsJob, ProjectorJob, SensorJob
from cell.calibration.validation_routine import ValidateJob
from cell.config import CellConfig, load_cell_config
from cell.controller import Controller, ControllerSettings, RobotLimits
from cell.devices import build_devices
from cell.errors import CalibrationError, ConfigError, RoutinePaused
from cell.planning.kinematics import UR5E
from cell.run_data import Checkpoint, Phase
from cell.runs import RunFolder, write_json_atomic
from cell.storage import new_folder, require_writable


# --------------------------------------------------------------------------------------------- runner
def _calibration_folder(
    out: Path,
    cell: Path | None,
    inputs: dict[str, Path] | None = None,
    kind: str = "",
    rerun_finished: bool = True,
) -> tuple[RunFolder, bool]:
    """The run folder ``out`` of a routine of ``kind``: a new one, an unfinished one to resume (True), or a
    finished one whose previous views and checkpoint are moved into ``previous-<time>/`` before a new attempt
    (refused unless ``rerun_finished``). A folder of another kind is refused. ``cell`` and ``inputs`` (name in
    inputs/ -> file) are copied into a new one, and its kind recorded (:meth:`RunFolder.mark_kind`)."""
    out = Path(out)
    if (out / "journal.jsonl").exists():
        run = RunFolder.open(out)
        held = run.kind
        if kind and held is not None and held != kind:
            raise ConfigError(
                f"this folder holds a '{held}' run, not '{kind}'; choose another --out", path=str(out)
            )
        cp = run.load_checkpoint()
        if cp is not None and Checkpoint.from_json(cp).phase is not Phase.DONE:
            return run, True
        if not rerun_finished:
            raise ConfigError(f"this {kind} run is already done; choose another --out", path=str(out))
        keep = out / f"previous-{time.strftime('%Y%m%dT%H%M%S')}"
        keep.mkdir()
        for name in ("views", "checkpoint.json"):
            if (out / name).exists():
                (out / name).rename(keep / name)
        (out / "views").mkdir()
    else:
        with new_folder(out):  # a full disk or read-only folder: refused, nothing left behind
            run = RunFolder.create(out.parent, "calibration", name=out.name)
            for name, path in {"cell.yaml": cell, **(inputs or {})}.items():
                if path is not None:
                    run.copy_input(path, name)
            run.mark_kind(kind)
    return run, False


def run_routine(
    job: CalibrationJob,
    out: Path,
    cell: Path | None = None,
    *,
    seed: int | None = None,
    on_progress: Callable[[Controller], None] | None = None,
    inputs: dict[str, Path] | None = None,
) -> dict[str, Any]:
    """Run ``job`` under the controller on the cell's devices (with a board stage) into run folder ``out``;
    an unfinished ``out`` is resumed. Returns the result (``job.result_file``); CalibrationError when the
    routine ended paused, faulted or aborted (the message says why; running it again resumes). ``inputs``
    are further files the run reads (copied into its inputs/). On a simulated cell the noise is drawn from
    the cell's ``sim.seed``, ``seed`` and the routine's kind together (fakes.sim_cell.noise_seed): each
    routine of one world, and each world of one ``seed``, sees its own camera noise and landing errors
    (docs/calibration.md); ``seed`` None: the cell's sim.seed alone, as an inspection uses."""
    cfg = job.cfg
    run, resume = _calibration_folder(out, cell, inputs, job.kind, job.rerun_finished)
    stream = () if seed is None else (seed, job.kind)
    devices = build_devices(cfg, stream=stream, with_stage=True)
    controller = Controller(
        devices,
        job,
        run,
        ControllerSettings(view_budget=10_000, max_iterations=1),
        robot_limits=RobotLimits.of(cfg.robot),
        home_joints_rad=np.deg2rad(cfg.robot.home_joints_deg),
        motion=JointMotion(UR5E),
        on_progress=on_progress,
    )
    state = controller.execute(resume=resume)
    if state == "paused":
        raise RoutinePaused(
            f"{job.kind} routine paused: {controller.message}; the same command with --out {run.path} "
            "resumes it"
        )
    if state != "done":
        raise CalibrationError(
            f"{job.kind} routine ended '{state}': {controller.message} (run folder {run.path}; run it "
            "again to resume)"
        )
    return json.loads((run.path / job.result_file).read_text())


def handeye_job(
    cfg: CellConfig, method: str = "icp", *, views: int = 12, force: bool = False, seed: int = 1
) -> CalibrationJob:
    """The hand-eye routine by ``method``: ICP of gauge scans against its CAD (``icp``) or AX = XB from
    ``views`` board poses (``tsai``, ``park``, ``daniilidis``)."""
    if method == "icp":
        return HandEyeIcpJob(cfg, force=force, seed=seed)
    if method in ("tsai", "park", "daniilidis"):
        return HandEyeBoardJob(cfg, views=views, method=method, force=force, seed=seed)
    raise ConfigError(
        f"unknown hand-eye method '{method}': use icp, tsai, park or daniilidis", field="method"
    )


def run_validation(
    cell: Path,
    out: Path,
    calibration: Path | None = None,
    gauge: Path | None = None,
    *,
    seed: int = 2,
    **options: Any,
) -> dict[str, Any]:
    """:class:`ValidateJob` of ``cell`` (``options``: its heights and sphere radius) run into ``out``, with
    the sensor ``calibration`` instead of the cell's active one when given, and the slot gauge's certificate
    ``gauge`` (default :data:`GAUGE_CERTIFICATE`) copied into the run; returns validation.json."""
    cfg = load_cell_config(cell)
    if calibration is not None:
        if not calibration.is_file():
            raise ConfigError("sensor calibration file not found; check the path", path=str(calibration))
        cfg.calibration.sensor = calibration.resolve()
    gauge = gauge or GAUGE_CERTIFICATE
    job = ValidateJob(cfg, seed=seed, gauge_certificate=gauge, **options)
    return run_routine(job, out, cell, seed=seed, inputs={"gauge.certificate.yaml": gauge})


ALL_STEPS = ("intrinsics", "projector", "kinematics", "validate")
FIELD = {
    "intrinsics": "intrinsics",
    "projector": "projector",
    "kinematics": "kinematics",
    "handeye": "hand_eye",
    "sensor": "sensor",
    "gamma": "gamma",
}


def calibrate_all(
    cell: Path,
    out: Path,
    *,
    sensor: bool = False,
    seed: int = 1,
    say: Callable[[str], None] = print,
) -> tuple[Path, dict[str, Any]]:
    """Chain the routines into ``out``: intrinsics -> projector -> robot kinematics with the hand-eye from
    board poses -> [per-pixel sensor] -> validation, each in ``out/<step>/`` and each using the calibrations
    before it. Writes ``out/cell.yaml`` (the cell config with its ``calibration:`` section pointing at the new
    files) and ``out/calibration.json``; returns (the cell file, the summary)."""
    cfg = load_cell_config(cell)
    out = Path(out)
    require_writable(out)  # a full disk or read-only folder: refused before the first routine
    out.mkdir(parents=True, exist_ok=True)
    steps: list[tuple[str, Callable[[CellConfig], CalibrationJob]]] = [
        ("intrinsics", lambda c: IntrinsicsJob(c, seed=seed)),
        ("projector", lambda c: ProjectorJob(c, views=12, seed=seed)),
        # the hand-eye found with the kinematics is the one that goes with them: an ICP hand-eye fitted over
        # them doubled the pose-dependent error at the part (0.11 -> 0.22 mm, docs/calibration.md)
        ("kinematics", lambda c: KinematicsJob(c, seed=seed)),
    ]
    if sensor:
        steps.append(("sensor", lambda c: SensorJob(c, seed=seed)))
    steps.append(("validate", lambda c: ValidateJob(c, seed=seed)))
    summary: dict[str, Any] = {}
    for name, make in steps:
        say(f"calibrate {name} -> {out / name}")
        t0 = time.perf_counter()
        result = run_routine(make(cfg), out / name, cell, seed=seed)
        summary[name] = {**result, "seconds": round(time.perf_counter() - t0, 1)}
        if name in FIELD:
            setattr(cfg.calibration, FIELD[name], Path(result["file"]).resolve())
        if name == "kinematics":  # the hand-eye found with the kinematics belongs to them
            cfg.calibration.hand_eye = (out / name / "handeye.yaml").resolve()
    data = yaml.safe_load(Path(cell).read_text())
    data["calibration"] = {k: str(v) for k, v in cfg.calibration.model_dump().items() if v is not None}
    cell_out = out / "cell.yaml"
    cell_out.write_text(yaml.safe_dump(data, sort_keys=False))
    load_cell_config(cell_out)  # the written config must load
    write_json_atomic(
        out / "calibration.json", {"cell": str(cell_out), "source_sha256": _digest(cell), "steps": summary}
    )
    return cell_out, summary


def _digest(path: Path) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def valid_calibration(cell: Path, folder: Path) -> Path | None:
    """``folder/cell.yaml`` when ``folder`` holds a finished `cell calibrate all` of exactly this ``cell``
    file (same content) whose calibrated config loads; else None."""
    summary, cell_out = Path(folder) / "calibration.json", Path(folder) / "cell.yaml"
    if not (summary.exists() and cell_out.exists()):
        return None
    if json.loads(summary.read_text()).get("source_sha256") != _digest(cell):
        return None
    try:
        load_cell_config(cell_out)
    except Exception:  # a calibration file moved or was damaged: calibrate again
        return None
    return cell_out


def ensure_calibration(cell: Path, folder: Path, say: Callable[[str], None] = print) -> Path:
    """The calibrated config of ``cell`` from ``folder``, running `cell calibrate all` there first when it
    holds no valid calibration of it (said through ``say``)."""
    found = valid_calibration(cell, folder)
    if found is not None:
        say(f"using the calibration in {folder} (made for {cell})")
        return found
    say(
        f"no valid calibration of {cell} in {folder}: running `cell calibrate all` there first "
        "(about two minutes)"
    )
    cell_out, _ = calibrate_all(cell, folder, say=say)
    return cell_out
