"""The controller end to end on a small simulated cell: states, guards, retries, pauses, resume, limits.

A small box part and the 160x120 test sensor keep each run to a few seconds. Every run's result is
compared with an uninterrupted reference run: a fault that was retried or resumed must not change a single
statistic.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cell.config import load_recipe
from cell.controller import Controller, ControllerSettings
from cell.devices import DeviceBundle, build_devices
from cell.errors import ConfigError
from cell.inspection import LambertianInspection, inspection_controller
from cell.mesh import load_part_W
from cell.run_data import Phase, View
from cell.runs import RunFolder
from cell.view_files import load_raw_stack
from tests.box_part import small_cell, write_box_recipe
from tests.same_result import assert_same_result
from tests.shared_runs import once_per_session


@pytest.fixture(scope="module")
def recipe_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_box_recipe(tmp_path_factory.mktemp("box"))


def make_controller(recipe_path: Path, run_dir: Path, **settings) -> tuple[Controller, DeviceBundle]:
    cfg = small_cell()
    recipe = load_recipe(recipe_path)
    nominal = trimesh.load(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())  # in {W}
    devices = build_devices(cfg, part_W=nominal, seed=5)
    job = LambertianInspection(recipe, cfg, nominal)
    job.settings.pictures = False
    job.settings.min_cluster_px = 20
    run = (
        RunFolder.open(run_dir)
        if (run_dir / "journal.jsonl").exists()
        else RunFolder.create(run_dir.parent, "box", name=run_dir.name)
    )
    # the recipe's view budget and feedback iterations, as `cell inspect` sets them (execute_run in
    # cell/inspection_run.py): once they are spent the run is judged, with no search for views it has no
    # room for
    limits = {"view_budget": recipe.plan.view_budget, "max_iterations": recipe.plan.max_iterations + 1}
    ctl = inspection_controller(
        devices, job, run, ControllerSettings(retry_delay_s=0.0, **{**limits, **settings})
    )
    return ctl, devices


def result_of(run_dir: Path) -> dict:
    doc = json.loads((run_dir / "results" / "report.json").read_text())
    return {"verdict": doc["verdict"], "n_points": doc["n_points"], "deviation": doc["deviation"]}


def _reference_run(folder: Path) -> dict:
    """An uninterrupted run of the box recipe (written into ``folder``, as :func:`recipe_path` writes it)."""
    run_dir = folder / "run"
    ctl, devices = make_controller(write_box_recipe(folder), run_dir)
    assert ctl.execute() == "done", ctl.message
    states = [e["state"] for e in RunFolder.open(run_dir).journal() if e["event"] == "state"]
    return {
        "result": result_of(run_dir),
        "states": states,
        "log": devices.robot.command_log,
        "views": len(ctl.checkpoint.views),
        "run_dir": run_dir,  # read only: a test that changes it copies it first
    }


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The uninterrupted reference run, made once per test session for the files that compare against it
    (this one, tests/test_controller_safety.py, tests/test_controller_overlap.py: tests/shared_runs.py)."""
    return once_per_session(tmp_path_factory, "box-controller-reference", _reference_run)


def test_uninterrupted_run_passes_through_every_phase(reference: dict) -> None:
    states = reference["states"]
    for expected in (
        "connecting",
        "homing",
        "planning",
        "scanning_moving",
        "scanning_capturing",
        "scanning_decoding",
        "evaluating",
        "registering",
        "reporting",
        "done",
    ):
        assert expected in states
    assert states.index("planning") < states.index("scanning_moving") < states.index("evaluating")
    assert reference["result"]["verdict"] == "pass"  # the simulator renders the nominal box itself
    assert reference["result"]["n_points"] > 1000


def test_robot_never_commanded_outside_envelope_or_limits(reference: dict) -> None:
    cfg = small_cell()
    lo, hi = np.array(cfg.robot.envelope_min_mm), np.array(cfg.robot.envelope_max_mm)
    moves = [e for e in reference["log"] if e["command"] in ("move_linear", "move_joint")]
    assert moves
    for e in moves:
        if e["command"] == "move_linear":
            p = np.asarray(e["target"])[:3, 3]
            assert np.all(p >= lo - 1e-6) and np.all(p <= hi + 1e-6)
            assert e["speed"] <= cfg.robot.max_tcp_speed_mm_s and e["accel"] <= cfg.robot.max_tcp_accel_mm_s2
        else:
            assert e["speed"] <= cfg.robot.max_joint_speed_rad_s
            assert e["accel"] <= cfg.robot.max_joint_accel_rad_s2


def test_no_motion_while_projector_is_not_ready(recipe_path: Path, tmp_path: Path) -> None:
    ctl, devices = make_controller(recipe_path, tmp_path / "run")
    devices.projector.faults.lamp_error = True
    assert ctl.execute() == "paused"
    assert "projector" in ctl.message and "lamp" in ctl.message
    assert not [e for e in devices.robot.command_log if e["command"].startswith("move")]


# Each retryable fault, injected in a step of its own of one run (a retry redoes the step it failed in): the
# first move loses the robot's connection, the first exposure's frame is lost, a later grab times out with its
# frame still coming, and the projector's serial line answers nothing, then garbage, to the status read after
# a later view's stack. The grab and trigger counts put them views apart (the box takes 34 frames a view).
GRAB_TIMEOUT_AT_GRAB = 80
SERIAL_TIMEOUT_AT_TRIGGER = 150
GARBLED_REPLY_AT_TRIGGER = 220


@pytest.fixture(scope="module")
def retried(recipe_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One run with the five retryable faults: its end state, the errors it journalled in order, and its
    result."""
    ctl, devices = make_controller(recipe_path, tmp_path_factory.mktemp("retried") / "run")
    camera, projector = devices.camera, devices.projector
    devices.robot.inject_fault("connection_loss")  # the next move, half way: the first
    camera.faults.drop_frames = 1  # the next exposure: the first view's first frame
    grab, trigger = camera.grab, camera.trigger
    calls = {"grab": 0, "trigger": 0}

    def grab_timing_out_once(timeout_ms: float):
        calls["grab"] += 1
        camera.faults.grab_timeout = calls["grab"] == GRAB_TIMEOUT_AT_GRAB
        return grab(timeout_ms)

    def trigger_then_line_faults() -> None:
        calls["trigger"] += 1
        if calls["trigger"] == SERIAL_TIMEOUT_AT_TRIGGER:
            projector.faults.serial_timeouts = 1
        elif calls["trigger"] == GARBLED_REPLY_AT_TRIGGER:
            projector.faults.garbled_replies = 1
        trigger()

    camera.grab, camera.trigger = grab_timing_out_once, trigger_then_line_faults
    state = ctl.execute()
    errors, capturing = [], None  # each error with the view whose capture last began before it
    for e in ctl.run.journal():
        if e["event"] == "capture":
            capturing = e["view"]
        elif e["event"] == "error":
            errors.append({**e, "capturing_view": capturing})
    return {"state": state, "message": ctl.message, "errors": errors, "result": result_of(ctl.run.path)}


def test_retryable_faults_end_in_done_with_identical_results(retried: dict, reference: dict) -> None:
    assert retried["state"] == "done", retried["message"]
    assert retried["errors"] and all(e["retryable"] for e in retried["errors"])
    assert_same_result(retried["result"], reference["result"], "retryable faults")


@pytest.mark.parametrize(
    "fault, kind, says, count",
    [
        ("connection_loss", "DeviceTimeout", "connection lost", 1),
        ("drop_frame and grab_timeout_once", "DeviceTimeout", "the frame was lost", 2),
        ("serial_timeout", "DeviceTimeout", "no reply to", 1),
        ("garbled_reply", "DeviceProtocolError", "garbled reply to", 1),
    ],
)
def test_each_retryable_fault_was_met_and_retried(
    retried: dict, fault: str, kind: str, says: str, count: int
) -> None:
    """Each fault of the shared run showed as the error it causes, retried (the next attempt went on)."""
    met = [e for e in retried["errors"] if e["kind"] == kind and says in e["error"]]
    assert len(met) == count, (fault, retried["errors"])
    assert all(e["retryable"] for e in met), fault


def test_the_dropped_frame_and_the_grab_timeout_are_met_views_apart(retried: dict) -> None:
    """Both faults say "the frame was lost": the dropped frame in the first view's capture, the grab timeout
    (grab 80, 34 frames a view) in a later view's, so each of the two errors is its own fault's."""
    lost = [e["capturing_view"] for e in retried["errors"] if "the frame was lost" in e["error"]]
    assert len(lost) == 2 and lost[0] == 0 and lost[1] >= 1, lost


PAUSING = ("protective_stop", "lamp_error_mid_run", "operator_pause")


def _inject_pausing_fault(ctl: Controller, devices: DeviceBundle, fault: str) -> None:
    """A protective stop on the next move, or the lamp failing / the operator pausing at the 40th trigger
    (in the second view of the run's part this controller does)."""
    if fault == "protective_stop":
        devices.robot.inject_fault("protective_stop")
        return
    original = devices.camera.trigger
    calls = {"n": 0}

    def trigger_then_fault() -> None:
        calls["n"] += 1
        if calls["n"] == 40:
            if fault == "lamp_error_mid_run":
                devices.projector.faults.lamp_error = True
            else:
                ctl.request_pause("test")
        original()

    devices.camera.trigger = trigger_then_fault


def keep_last_stacks(ctl: Controller) -> dict[int, np.ndarray]:
    """The captured stacks of the views the job's decode keeps back (each plan's last view, ``last``), by
    view, copied before the decode takes them: the truth for the raw images written later."""
    decode, kept = ctl.job.decode, {}

    def decode_keeping_last_stacks(view, captured, out_dir):
        if captured.last:
            kept[captured.index] = np.array(captured.images, copy=True)
        return decode(view, captured, out_dir)

    ctl.job.decode = decode_keeping_last_stacks
    return kept


def _pause_after_last_evaluation(ctl: Controller) -> None:
    """Ask for a pause once the evaluation has qualified the views (no replan follows): after the last view's
    decode, before the registration is taken and the verdict is out."""
    done = ctl.job.evaluations_done

    def done_then_pause() -> None:
        done()
        ctl.request_pause("test, after the last evaluation")

    ctl.job.evaluations_done = done_then_pause


@pytest.fixture(scope="module")
def paused_and_resumed(recipe_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One run paused by each pausing fault in turn: the run pauses (a protective stop on its first move), a
    new controller (a new process, the operator having fixed the cause) resumes it from the run folder, that
    one pauses (the lamp fails), the next resumes it and is paused by the operator, the next resumes it and
    is paused after its last evaluation (its last view decoded, no verdict yet), and the last resumes it to
    the end. Per fault: the state and message its controller ended in and the journal's length then;
    the last view's captured stack and its raw images as read back at that last pause; and the run's end and
    result."""
    run_dir = tmp_path_factory.mktemp("paused") / "run"
    stages = {}
    for i, fault in enumerate(PAUSING):
        ctl, devices = make_controller(recipe_path, run_dir)
        _inject_pausing_fault(ctl, devices, fault)
        state = ctl.execute(resume=i > 0)
        stages[fault] = {"state": state, "message": ctl.message, "journal": len(ctl.run.journal())}
    ctl, _ = make_controller(recipe_path, run_dir)
    kept = keep_last_stacks(ctl)
    _pause_after_last_evaluation(ctl)
    state = ctl.execute(resume=True)
    last = len(ctl.checkpoint.views) - 1
    at_pause = {
        "state": state,
        "message": ctl.message,
        "journal": len(ctl.run.journal()),
        "phase": ctl.checkpoint.phase,
        "last": last,
        "captured": kept.get(last),
        "raw": load_raw_stack(ctl.run.view_dir(last)),
    }
    ctl, _ = make_controller(recipe_path, run_dir)
    state = ctl.execute(resume=True)
    result = result_of(run_dir) if state == "done" else None
    return {
        "stages": stages,
        "at_pause": at_pause,
        "state": state,
        "message": ctl.message,
        "journal": len(ctl.run.journal()),
        "result": result,
        "run_dir": run_dir,
    }


@pytest.mark.parametrize("fault", PAUSING)
def test_pausing_faults_pause_and_the_next_process_resumes(paused_and_resumed: dict, fault: str) -> None:
    stage = paused_and_resumed["stages"][fault]
    assert stage["state"] == "paused", (fault, stage["message"])
    says = {"protective_stop": "protective stop", "lamp_error_mid_run": "lamp", "operator_pause": "test"}
    assert says[fault] in stage["message"], stage["message"]
    # the next process resumed it: nothing of this part was lost, the journal went on
    later = [s["journal"] for s in paused_and_resumed["stages"].values()]
    later += [paused_and_resumed["at_pause"]["journal"], paused_and_resumed["journal"]]
    assert later[PAUSING.index(fault) + 1] > stage["journal"]


def test_pausing_faults_resume_to_identical_results(paused_and_resumed: dict, reference: dict) -> None:
    assert paused_and_resumed["state"] == "done", paused_and_resumed["message"]
    assert_same_result(paused_and_resumed["result"], reference["result"], "paused four times")


def test_a_run_paused_before_its_verdict_keeps_its_last_views_raw_images(paused_and_resumed: dict) -> None:
    """The run paused after its last evaluation (the last view decoded, its raw stack held back for after
    the verdict, no verdict yet) writes that stack into the view's folder on its way out: a whole capture
    folder that the project's reader gives back equal to the stack the camera captured, journalled once; the
    resumed run does not write it again and leaves it as it was."""
    at_pause = paused_and_resumed["at_pause"]
    assert at_pause["state"] == "paused" and "after the last evaluation" in at_pause["message"]
    assert at_pause["phase"] is Phase.REGISTERING  # paused before the registration and the verdict
    captured, raw = at_pause["captured"], at_pause["raw"]
    assert captured is not None and raw is not None
    assert raw.dtype == captured.dtype and np.array_equal(raw, captured)
    run = RunFolder.open(paused_and_resumed["run_dir"])
    last = at_pause["last"]
    assert (run.view_dir(last) / "raw" / "capture.yaml").is_file()
    journal = run.journal()
    written = [e for e in journal if e["event"] == "written_on_stop"]
    assert len(written) == 1 and written[0]["view"] == last and written[0]["state"] == "paused"
    assert written[0]["raw_images_bytes"] > 0
    assert not [e for e in journal if e["event"] == "error" and e.get("kind") == "on_stop"]
    assert np.array_equal(load_raw_stack(run.view_dir(last)), captured)  # after the resume to the end


def test_recipe_regions_are_judged_with_their_own_bands(
    recipe_path: Path, reference: dict, tmp_path: Path
) -> None:
    """The reference run (the simulator renders the nominal box, so every point is within a few um of it)
    reported again with recipe regions: a band of +-1 um (the narrowest a recipe accepts: nearer zero is a
    value in metres) on the top face must fail on the sensor noise alone, and locate its out-of-tolerance
    points on the top face (z = 40 mm); a loose band passes."""
    run_dir = tmp_path / "run"
    shutil.copytree(reference["run_dir"], run_dir)
    data = yaml.safe_load(recipe_path.read_text())
    box = trimesh.load(recipe_path.parent / data["part"]["cad"])
    sides = [int(i) for i in np.flatnonzero(np.abs(box.face_normals[:, 2]) < 0.5)]
    data["regions"] = [
        {"name": "top", "box_mm": [[-61, -46, 39], [61, 46, 41]], "tolerance_mm": [-0.001, 0.001]},
        {"name": "sides", "faces": sides, "tolerance_mm": [-1.0, 1.0]},
    ]
    (recipe_path.parent / "box_regions.yaml").write_text(yaml.safe_dump(data))
    recipe = load_recipe(recipe_path.parent / "box_regions.yaml")
    job = LambertianInspection(recipe, small_cell(), box.copy().apply_transform(recipe.part.T_W_P.matrix()))
    job.settings.pictures = False
    run = RunFolder.open(run_dir)
    summary = job.report(run, run.load_checkpoint()["registration"])
    doc = json.loads((run_dir / "results" / "report.json").read_text())
    assert reference["result"]["verdict"] == "pass" and summary["verdict"] == "fail"
    verdicts = {r["name"]: r for r in doc["region_verdicts"]}
    assert verdicts["top"]["verdict"] == "fail" and verdicts["sides"]["verdict"] == "pass"
    assert verdicts["top"]["n_points"] > 100 and verdicts["sides"]["n_points"] > 100
    assert doc["n_out_of_tolerance"] > 0 and doc["regions"]
    assert all(abs(r["centre_mm"][2] - 40.0) < 1.0 for r in doc["regions"])


def test_recipe_region_with_a_face_the_cad_lacks_is_refused(recipe_path: Path) -> None:
    data = yaml.safe_load(recipe_path.read_text())
    data["regions"] = [{"name": "pad", "faces": [0, 12]}]  # the box has 12 faces: 0..11
    bad = recipe_path.parent / "box_bad_region.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="face 12") as err:
        load_part_W(load_recipe(bad), bad, small_cell())
    assert str(bad) in str(err.value) and "regions.0.faces" in str(err.value)
    data["regions"] = [{"name": "pad", "faces": [1]}, {"name": "pad", "box_mm": [[0, 0, 0], [1, 1, 1]]}]
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="repeated: pad"):
        load_recipe(bad)


def test_the_registration_finishes_a_cut_and_merge_made_ahead_when_the_last_views_refinement_allows(
    reference: dict,
) -> None:
    """Each round's last view: the views before it were refined jointly and cut and merged ahead, while the
    robot moved to it (the job's decode of the view before it starts that); the registration says which
    merge it took. It may take the one made ahead only when the last view left the earlier views'
    corrections as they were to the bit, i.e. when the last view is held at its kinematic pose (a registered
    one moves the others on: cell.analysis.view_refinement.refine_newest); the cloud is the same either way
    (tests/test_analysis_merge.py, tests/test_inspect_e2e.py)."""
    journal = RunFolder.open(reference["run_dir"]).journal()
    records = [e for e in journal if e["event"] == "merge_ahead"]
    registration = [e for e in journal if e["event"] == "registration"][-1]
    assert records, "no cut and merge was made ahead of the last view"
    last = reference["views"] - 1
    held_last = last in registration["refinement"]["unregistered_views"]
    assert records[-1]["views"] == last  # all the views before the last
    assert records[-1]["used"] == held_last, (records[-1], registration["refinement"])
    assert not [e for e in journal if e["event"] == "error" and e.get("kind") == "merge ahead"]


def test_the_first_plans_last_view_keeps_its_raw_images_when_more_views_follow(reference: dict) -> None:
    """The raw images of the first plan's last view, kept back by its decode (cell.inspection
    ``_write_raw_later``), are written into its committed folder beside the next view's decode once the
    feedback loop asks for more views: a whole capture folder (manifest, every frame), as the views decoded
    before it have, and of a view of its own (not another view's frames); the last plan's last view's are not
    written at all (the passed run's retention keeps none: raw_images_passed_days 0)."""
    from cell.run_data import Checkpoint

    run = RunFolder.open(reference["run_dir"])
    views = Checkpoint.from_json(run.load_checkpoint()).views
    first = [i for i, v in enumerate(views) if v.iteration == 0]
    assert reference["result"]["verdict"] == "pass" and len(views) > len(first)  # a feedback round followed
    assert run.completed_views() == list(range(len(views)))
    stacks = {i: load_raw_stack(run.view_dir(i)) for i in (first[-2], first[-1], first[-1] + 1)}
    kept = stacks[first[-1]]
    assert (run.view_dir(first[-1]) / "raw" / "capture.yaml").is_file() and kept is not None
    for i, stack in stacks.items():
        assert stack is not None and stack.shape == kept.shape and stack.dtype == kept.dtype, i
        assert i == first[-1] or not np.array_equal(stack, kept), i
    frames = list((run.view_dir(first[-1]) / "raw").rglob("*.png"))
    assert kept.shape[1:] == (120, 160) and len(frames) == len(kept)
    assert not (run.view_dir(len(views) - 1) / "raw").exists()


# ---------------------------------------------------------------- the controller alone, with a job of its own
# A job and devices that do nothing but record what the controller asks of them: the controller's own
# sequencing (the registration ahead, its call-off, the exit hook) in well under a second.


class _StubDevice:
    """A robot, projector or camera that is always ready and records the moves it is sent."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.moves: list[np.ndarray] = []

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def switch_on(self) -> None: ...

    def blank(self) -> None: ...

    def stop(self) -> None: ...

    def ready(self) -> bool:
        return True

    def state(self):
        from types import SimpleNamespace

        return SimpleNamespace(normal=True, why_not_normal=None)

    def move_linear(self, target: np.ndarray, speed: float, accel: float) -> None:
        self.moves.append(np.asarray(target))


def _stub_devices() -> DeviceBundle:
    return DeviceBundle(
        robot=_StubDevice("robot"), camera=_StubDevice("camera"), projector=_StubDevice("projector")
    )  # type: ignore[arg-type]


class _SlowRegistrationJob:
    """A job whose registration is slower than its evaluation: ``register`` (started ahead, in the worker,
    beside ``evaluate``) runs until its ``stop`` event is set, or, once an evaluation has qualified the views,
    to its end; the first evaluation asks for one more view (after the registration has started, so that
    there is one to call off). ``pause_in_first_evaluation``: the controller is asked to pause from inside the
    first evaluation instead. Everything the controller asks is recorded."""

    part_name = "stub"
    register_while_evaluating = True
    TIMEOUT_S = 10.0  # a registration that nobody calls off fails the test after this

    def __init__(self) -> None:
        self.registrations: list[dict] = []  # per register call: views, how it ended, whether stop was set
        self.registering = threading.Event()  # a registration is running
        self.qualified = threading.Event()  # an evaluation qualified the views: the registration may end
        self.evaluations: list[int] = []  # the number of views of each evaluation
        self.stops: list[str] = []  # the states on_stop was called with
        self.controller: Controller | None = None
        self.pause_in_first_evaluation = False

    def plan(self) -> list[View]:
        return [View(np.eye(4), iteration=0), View(np.eye(4), iteration=0)]

    def capture(self, devices, view, index, views):
        return index

    def decode(self, view, captured, out_dir: Path) -> dict:
        (out_dir / "view.json").write_text(json.dumps({"view": captured}))
        return {"view": captured}

    def evaluate(self, run, views, iteration):
        from cell.run_data import Evaluation

        assert self.registering.wait(self.TIMEOUT_S), "no registration was started beside the evaluation"
        self.evaluations.append(len(views))
        if len(self.evaluations) == 1 and self.pause_in_first_evaluation:
            assert self.controller is not None
            self.controller.request_pause("test, while the registration runs ahead")
        qualified = len(self.evaluations) > 1
        if qualified:
            self.qualified.set()
        return Evaluation(qualified, 0.0 if qualified else 1.0, iteration)

    def replan(self, run, views, evaluation):
        return [View(np.eye(4), iteration=evaluation.iteration + 1)]

    def register(self, run, views, stop: threading.Event | None = None) -> dict:
        from cell.errors import CalledOff

        entry = {"views": len(views), "ended": None, "stop_seen": False}
        self.registrations.append(entry)
        self.registering.set()
        deadline = time.monotonic() + self.TIMEOUT_S
        while not self.qualified.is_set():  # one step of the registration after another
            if stop is not None and stop.is_set():
                entry["ended"], entry["stop_seen"] = "called off", True
                self.registering.clear()
                raise CalledOff("registration")
            if time.monotonic() > deadline:
                entry["ended"] = "timed out"
                raise TimeoutError("the registration was never called off")
            time.sleep(0.001)
        entry["ended"] = "finished"
        return {"n_points": 10 * len(views)}

    def report(self, run, registration):
        return {"n_points": registration["n_points"]}

    def on_stop(self, run, state: str) -> dict:
        self.stops.append(state)
        return {"held": 1}


def _stub_run(tmp_path: Path, job: _SlowRegistrationJob) -> Controller:
    run = RunFolder.create(tmp_path, "stub", name="run")
    ctl = Controller(_stub_devices(), job, run, ControllerSettings(retry_delay_s=0.0))  # type: ignore[arg-type]
    job.controller = ctl
    return ctl


def test_a_registration_slower_than_the_evaluation_is_called_off_by_the_replan(tmp_path: Path) -> None:
    """The first evaluation asks for more views while the registration started beside it still runs: the
    replan sets its stop event, the registration stops (journalled ``registration_called_off``), the new
    view is measured, and the registration of all three views, started beside the second evaluation, runs
    to its end once and is the one reported; the run ends ``done`` (no exit hook)."""
    job = _SlowRegistrationJob()
    ctl = _stub_run(tmp_path, job)
    assert ctl.execute() == "done", ctl.message
    assert job.evaluations == [2, 3]
    assert job.registrations == [
        {"views": 2, "ended": "called off", "stop_seen": True},
        {"views": 3, "ended": "finished", "stop_seen": False},
    ]
    journal = ctl.run.journal()
    events = [e["event"] for e in journal]
    called_off = [e for e in journal if e["event"] == "registration_called_off"]
    assert len(called_off) == 1 and called_off[0]["views"] == 2
    assert events.index("registration_called_off") < events.index("replan")  # the replan waited for it
    assert [e["n_new"] for e in journal if e["event"] == "replan"] == [1]
    assert [e["n_points"] for e in journal if e["event"] == "registration"] == [30]
    assert not [e for e in journal if e["event"] == "error"]
    assert ctl.run.completed_views() == [0, 1, 2] and len(ctl.devices.robot.moves) == 3
    assert job.stops == [] and "written_on_stop" not in events


def test_a_pause_drops_the_registration_running_ahead_and_calls_the_exit_hook(tmp_path: Path) -> None:
    """A pause asked for while the registration runs ahead of the evaluation: the registration is called
    off (the run does not wait for it to end), the run pauses, and the job's ``on_stop`` is called once,
    with ``paused``, what it returned journalled; an ``on_stop`` that raises is journalled, not raised."""
    job = _SlowRegistrationJob()
    job.pause_in_first_evaluation = True
    ctl = _stub_run(tmp_path, job)
    assert ctl.execute() == "paused", ctl.message
    assert job.registrations == [{"views": 2, "ended": "called off", "stop_seen": True}]
    assert job.stops == ["paused"]
    journal = ctl.run.journal()
    written = [e for e in journal if e["event"] == "written_on_stop"]
    assert len(written) == 1 and written[0]["state"] == "paused" and written[0]["held"] == 1
    assert [e["state"] for e in journal if e["event"] == "exit"] == ["paused"]

    def failing_on_stop(run, state):
        raise RuntimeError("injected on_stop failure")

    job2 = _SlowRegistrationJob()
    job2.pause_in_first_evaluation = True
    job2.on_stop = failing_on_stop  # type: ignore[method-assign]
    ctl2 = _stub_run(tmp_path / "second", job2)
    assert ctl2.execute() == "paused", ctl2.message
    journal = ctl2.run.journal()
    errors = [e for e in journal if e["event"] == "error" and e["kind"] == "on_stop"]
    assert len(errors) == 1 and "injected on_stop failure" in errors[0]["error"]
    assert [e["state"] for e in journal if e["event"] == "exit"] == ["paused"]
