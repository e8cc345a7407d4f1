# ruff: noqa: F811  (the fixtures recipe_path and reference come from tests/test_controller.py)
"""Fault matrix, robot safety: a safeguard stop, a watchdog trip, a pause mid-move, SIGTERM mid-move through
the CLI, and a stale run-folder lock. Each ends in a defined state (paused, with the arm stopped where the
simulated physics says), loses no view, and `resume` ends with the result of an uninterrupted run. The first
three pause one run in turn, each resuming what the one before paused.

Truth: the simulated arm's motion on its own clock (trapezoid profiles, a deceleration at the configured
maximum acceleration after a stop), and the uninterrupted reference run of tests/test_controller.py.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from cell.controller import Controller
from cell.devices import DeviceBundle
from cell.runs import RunFolder
from tests import cli_process
from tests.box_part import small_cell
from tests.browser import require_chromium
from tests.same_result import assert_same_result, judged_report
from tests.shared_runs import OPERATOR, box_cli_reference
from tests.test_controller import make_controller, recipe_path, reference, result_of  # noqa: F401

REPO = Path(__file__).resolve().parent.parent


def _moves(log: list[dict]) -> list[dict]:
    return [e for e in log if e["command"] in ("move_linear", "move_joint")]


def _views_in_journal(run_dir: Path) -> set[int]:
    return {e["view"] for e in RunFolder.open(run_dir).journal() if e["event"] == "view"}


@pytest.fixture(scope="module")
def paused_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run folder the three in-process tests below pause in turn, in file order (a safeguard stop, a
    watchdog trip, a pause mid-move; each test's controller a new process that resumes the run the last one
    paused), and the fourth resumes to its end: one run, not three (a test run alone starts the run)."""
    return tmp_path_factory.mktemp("paused") / "run"


def _go_on(recipe_path: Path, run_dir: Path) -> tuple[Controller, DeviceBundle, Callable[[], str]]:
    """A controller for the run in ``run_dir`` (a new one, or the paused one resumed), its devices, and the
    call that executes it and checks that the views done before it are still done and the journal went on."""
    ctl, devices = make_controller(recipe_path, run_dir)
    resumed = (run_dir / "journal.jsonl").exists()
    views_before = set(RunFolder.open(run_dir).completed_views()) if resumed else set()
    journal_before = len(RunFolder.open(run_dir).journal()) if resumed else 0

    def execute() -> str:
        state = ctl.execute(resume=resumed)
        assert views_before <= set(ctl.run.completed_views())  # no view lost
        assert len(ctl.run.journal()) > journal_before
        return state

    return ctl, devices, execute


def test_safeguard_stop_mid_move_pauses_and_resumes(recipe_path: Path, paused_run: Path) -> None:
    """A guard opens during a move: the arm stops on its path, the run pauses naming the safeguard stop and
    refuses to move while the guard is open; after the reset the next test's controller resumes it."""
    ctl, devices, execute = _go_on(recipe_path, paused_run)
    original = devices.camera.trigger
    calls = {"n": 0}

    def trigger_then_open_the_guard() -> None:  # after a few views: the next move meets the open guard
        calls["n"] += 1
        if calls["n"] == 40:
            devices.robot.inject_fault("safeguard_stop")  # half way through the next move
        original()

    devices.camera.trigger = trigger_then_open_the_guard
    assert execute() == "paused", ctl.message
    assert "safeguard stop" in ctl.message
    stopped = [e for e in _moves(devices.robot.command_log) if e["outcome"] == "safeguard_stop"]
    assert len(stopped) == 1 and stopped[0]["duration_s"] > 0.0
    devices.robot.connect()
    state = devices.robot.state()
    assert state.safeguard_stop and not state.normal and "safeguard" in state.why_not_normal


def test_watchdog_trip_stops_the_arm_within_the_period(recipe_path: Path, paused_run: Path) -> None:
    """The controlling code stops kicking mid-move (as when its process dies or hangs): the simulated arm
    starts to decelerate one watchdog period after the last kick and stands still after at most v/a more,
    never reaching its target; the run pauses, for the next test's controller to resume."""
    ctl, devices, execute = _go_on(recipe_path, paused_run)
    robot = devices.robot
    period = robot.watchdog_period_s
    assert period == pytest.approx(0.1)  # default 10 Hz, like ur_rtde's setWatchdog()
    kick = robot.kick_watchdog
    alive = {"kicks": 0, "last": None}

    def kick_until_dead() -> None:  # 250 polls (1 s of motion) after the start, the controller "dies"
        alive["kicks"] += 1
        if alive["kicks"] <= 250:
            alive["last"] = robot.clock.now()
            kick()

    robot.kick_watchdog = kick_until_dead
    assert execute() == "paused", ctl.message
    assert "watchdog" in ctl.message
    tripped = [e for e in _moves(robot.command_log) if e["outcome"] == "watchdog"]
    assert len(tripped) == 1
    end = tripped[0]["start_s"] + tripped[0]["duration_s"]
    cfg = small_cell().robot
    worst_stop = max(
        cfg.max_tcp_speed_mm_s / cfg.max_tcp_accel_mm_s2,
        cfg.max_joint_speed_rad_s / cfg.max_joint_accel_rad_s2,
    )
    assert alive["last"] + period <= end + 1e-9 <= alive["last"] + period + worst_stop + 1e-9
    if tripped[0]["command"] == "move_linear":
        target = np.asarray(tripped[0]["target"])[:3, 3]
        robot.connect()
        assert np.linalg.norm(robot.tool_pose()[:3, 3] - target) > 1.0  # it did not finish the move


def test_pause_mid_move_stops_the_arm_at_once(recipe_path: Path, paused_run: Path) -> None:
    """request_pause (what Ctrl-C and SIGTERM call) during a move: the arm decelerates from that instant,
    the move ends within the stop ramp (no wait for the move to end), the run pauses."""
    ctl, devices, execute = _go_on(recipe_path, paused_run)
    robot = devices.robot
    wait = robot.wait
    polls = {"n": 0, "t": None}

    def wait_then_pause(timeout_s: float = 0.004) -> bool:
        polls["n"] += 1
        if polls["n"] == 400:  # 1.6 s of motion into the run: some move is under way
            polls["t"] = robot.clock.now()
            ctl.request_pause("test")
        return wait(timeout_s)

    robot.wait = wait_then_pause
    assert execute() == "paused", ctl.message
    assert ctl.message.startswith("pause requested: test") and "stopped" in ctl.message
    stopped = [e for e in _moves(robot.command_log) if e["outcome"] == "stopped"]
    assert len(stopped) == 1
    end = stopped[0]["start_s"] + stopped[0]["duration_s"]
    cfg = small_cell().robot
    worst_stop = max(
        cfg.max_tcp_speed_mm_s / cfg.max_tcp_accel_mm_s2,
        cfg.max_joint_speed_rad_s / cfg.max_joint_accel_rad_s2,
    )
    assert polls["t"] <= end <= polls["t"] + worst_stop + 1e-9
    assert not [e for e in _moves(robot.command_log) if e["start_s"] > polls["t"]]  # nothing sent after


def test_the_run_paused_three_times_resumes_to_the_reference_result(
    recipe_path: Path, paused_run: Path, reference: dict
) -> None:
    # the three tests above paused this run, in file order; run alone, there is nothing here to resume
    journal = RunFolder.open(paused_run).journal() if (paused_run / "journal.jsonl").exists() else []
    pauses = [e["message"] for e in journal if e["event"] == "state" and e["state"] == "paused"]
    assert len(pauses) == 3, f"the three tests above pause this run (run the whole file): {pauses}"
    assert "safeguard stop" in pauses[0] and "watchdog" in pauses[1], pauses
    assert pauses[2].startswith("pause requested: test"), pauses
    ctl, _, execute = _go_on(recipe_path, paused_run)
    assert execute() == "done", ctl.message
    assert_same_result(result_of(paused_run), reference["result"], "safeguard stop, watchdog, pause mid-move")


# ------------------------------------------------------------------------------------------ CLI, processes
def _cell(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cell", *args], capture_output=True, text=True, cwd=REPO, timeout=timeout
    )


@pytest.fixture(scope="module")
def box_inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The box recipe and the small cell as a file. A test that needs a signal to arrive mid-move paces the
    simulated arm of one process through CELL_SIM_REALTIME_FACTOR (fakes/robot.py), which leaves the cell
    config, and so the run's record of its inputs, as it is."""
    recipe, cell_file, _ = box_cli_reference(tmp_path_factory)
    return recipe, cell_file


@pytest.fixture(scope="module")
def cli_forks() -> Iterator[None]:
    """The server that forks this module's `cell` processes after the first with the CLI already imported
    (tests/cli_process.py): each is the CLI's entry point in a process of its own, without ~3 s of imports."""
    with cli_process.server():
        yield


def _forked(log: Path, *args: str) -> subprocess.CompletedProcess:
    """`cell ARGS` in a forked process (see :func:`cli_forks`), its output in ``log``."""
    return cli_process.run(list(args), log)


@pytest.fixture(scope="module")
def cli_reference_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run folder of an uninterrupted `cell inspect` of the box (same inputs, seed and settings; the
    serial SN-7 and the operator OPERATOR given), made once per test session (tests/shared_runs.py)."""
    return box_cli_reference(tmp_path_factory)[2]


@pytest.fixture(scope="module")
def cli_reference(cli_reference_run: Path) -> dict:
    """The report of the uninterrupted `cell inspect` of the box."""
    return json.loads((cli_reference_run / "results" / "report.json").read_text())


@pytest.mark.chromium
def test_cell_report_rebuilds_from_the_stored_cloud_and_prints(
    cli_reference_run: Path, cli_reference: dict, cli_forks: None, tmp_path: Path
) -> None:
    """`cell report RUN --pdf --csv`: the same result rebuilt from results/cloud.ply (the cloud stored once:
    no other copy of it in results/), the CSV on request, and a PDF of at most three pages that names the
    part's serial; the operator's name reaches the page escaped."""
    require_chromium()
    from pypdf import PdfReader

    run = tmp_path / "run"
    shutil.copytree(cli_reference_run, run)
    results = run / "results"
    assert sorted(p.name for p in results.iterdir()) == ["cloud.ply", "report.html", "report.json"]
    doc = judged_report(_forked(tmp_path / "report.log", "report", str(run), "--pdf", "--csv"), run)
    assert_same_result(doc, cli_reference, "cell report")
    assert doc["metadata"]["run"]["identity"] == {"serial": "SN-7", "operator": OPERATOR, "order": None}
    rows = (results / "deviations.csv").read_text().count("\n") - 1
    assert rows == doc["n_points"]
    pages = PdfReader(results / "report.pdf").pages
    assert 1 <= len(pages) <= 3 and "SN-7" in pages[0].extract_text() and "PASS" in pages[0].extract_text()
    page = (results / "report.html").read_text()
    assert OPERATOR not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page


def _motions(log: Path) -> list[dict]:
    """The moves the simulated arm has started (CELL_SIM_MOTION_LOG), the last line only when complete."""
    if not log.exists():
        return []
    return [json.loads(line) for line in log.read_text().splitlines(keepends=True) if line.endswith("\n")]


def _journal(run: Path) -> list[dict]:
    if not (run / "journal.jsonl").exists():
        return []
    return RunFolder(run).journal()


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_sigterm_mid_move_pauses_and_resume_gives_the_same_result(
    box_inputs: tuple[Path, Path], cli_reference: dict, tmp_path: Path
) -> None:
    recipe, cell_file = box_inputs
    run = tmp_path / "run"
    motions = tmp_path / "motions.jsonl"  # the simulated arm appends a line as each move starts
    # the arm moves at a quarter of wall-clock speed (a 1 s move lasts 4 s) in this process only, and says
    # when each move starts (fakes/robot.py): the signal goes once the arm is in motion, however loaded the
    # machine
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "inspect", str(recipe), "--cell", str(cell_file), "--out", str(run)],
        cwd=REPO,
        env={**os.environ, "CELL_SIM_REALTIME_FACTOR": "0.25", "CELL_SIM_MOTION_LOG": str(motions)},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    deadline = time.monotonic() + 300
    try:  # wait for the second view's first move to start, then terminate the process mid-move
        while time.monotonic() < deadline and proc.poll() is None:
            moves = [e for e in _journal(run) if e["event"] == "device" and (e.get("view") or 0) >= 1]
            # the journal logs a move before the controller sends it (the arm is not moving yet: a signal
            # then pauses the run before the move); the arm's own line says it started
            if moves and any(
                m["command"] == moves[0]["command"] and np.allclose(m["target"], moves[0]["target"])
                for m in _motions(motions)
            ):
                break
            time.sleep(0.01)
        assert proc.poll() is None, "the run ended before it could be terminated"
        os.kill(proc.pid, signal.SIGTERM)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 3, out  # EXIT_PAUSED
    assert "SIGTERM" in out and "cell resume" in out
    journal = _journal(run)
    stops = [e for e in journal if e["event"] == "error" and e["kind"] == "MotionStopped"]
    assert stops and "into the move" in stops[0]["error"], "the arm was not stopped mid-move"
    exits = [e for e in journal if e["event"] == "exit"]
    assert exits[-1]["state"] == "paused"  # (the results database's record of it follows)
    assert not (run / "run.lock").exists()  # released on the way out
    views_before = set(RunFolder.open(run).completed_views())
    done = _cell("resume", str(run))
    doc = judged_report(done, run)
    assert views_before <= set(RunFolder.open(run).completed_views())
    assert_same_result(doc, cli_reference, "SIGTERM mid-move")


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_stale_lock_is_taken_over_and_a_live_one_refused(
    box_inputs: tuple[Path, Path], cli_reference: dict, cli_forks: None, tmp_path: Path
) -> None:
    """A run paused by SIGTERM is left with the lock of a process that died (as after a SIGKILL or a power
    cut): `cell resume` takes it over and journals it. While a live process holds the lock, `cell resume`
    and `cell inspect --out` on the folder are refused naming its PID and host, and nothing is written."""
    recipe, cell_file = box_inputs
    run = tmp_path / "run"
    proc = cli_process.start(
        ["inspect", str(recipe), "--cell", str(cell_file), "--out", str(run)], tmp_path / "inspect.log"
    )
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.is_alive():
        if any(e["event"] == "view" for e in _journal(run)):
            break
        time.sleep(0.05)
    proc.kill()  # SIGKILL: no handler runs, the lock stays behind
    proc.join(timeout=30)
    assert proc.exitcode == -signal.SIGKILL
    holder = json.loads((run / "run.lock").read_text())
    assert holder["pid"] == proc.pid

    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:  # a live holder: a second process is refused with its name
        live = dict(holder, pid=sleeper.pid, start=None, command="cell resume")
        (run / "run.lock").write_text(json.dumps(live))
        journal_before = (run / "journal.jsonl").read_bytes()
        refused = _forked(tmp_path / "refused-resume.log", "resume", str(run))
        assert refused.returncode == 2
        assert f"PID {sleeper.pid}" in refused.stdout + refused.stderr
        assert holder["host"] in refused.stdout + refused.stderr
        inspect = ("inspect", str(recipe), "--cell", str(cell_file), "--out", str(run))
        refused = _forked(tmp_path / "refused-inspect.log", *inspect)
        assert refused.returncode == 2 and f"PID {sleeper.pid}" in refused.stdout + refused.stderr
        assert (run / "journal.jsonl").read_bytes() == journal_before
    finally:
        sleeper.kill()
        sleeper.wait()

    (run / "run.lock").write_text(json.dumps(dict(holder, pid=_dead_pid())))
    done = _forked(tmp_path / "resume.log", "resume", str(run))
    judged_report(done, run)
    takeovers = [e for e in _journal(run) if e["event"] == "lock"]
    assert takeovers and takeovers[0]["action"] == "stale lock taken over"
    assert not (run / "run.lock").exists()
    assert_same_result(json.loads((run / "results" / "report.json").read_text()), cli_reference, "stale lock")
