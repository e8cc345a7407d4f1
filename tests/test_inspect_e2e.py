"""`cell inspect` end to end through the CLI: the pillar's dent is found where it is; a killed run resumes.
(The good pillar passing, its springback bow shown, is tests/test_inspect_alignment.py's inspection.)

The binned simulated cell (recipes/cells/sim_binned.yaml: the prototype with its camera binned 2x2) keeps a
full pillar inspection to about half a minute. The kill test uses a small box part for speed, and kills
resumes too (chains of kills), so that 20 kills cost about two runs, not twenty.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cell.errors import CalledOff
from cell.exit_codes import ExitCode
from tests import cli_process
from tests.same_result import assert_same_result, judged_report
from tests.shared_runs import box_cli_reference

REPO = Path(__file__).resolve().parent.parent
BINNED = REPO / "recipes" / "cells" / "sim_binned.yaml"
PILLAR = REPO / "recipes" / "pillar.yaml"

pytestmark = pytest.mark.slow


def cell(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cell", *args], capture_output=True, text=True, cwd=REPO, timeout=timeout
    )


def report(run: Path) -> dict:
    return json.loads((run / "results" / "report.json").read_text())


def test_dented_pillar_fails_with_the_dent_located(tmp_path: Path) -> None:
    proc = cell("inspect", str(PILLAR), "--cell", str(BINNED), "--out", str(tmp_path / "run"))
    assert proc.returncode == ExitCode.FAIL, proc.stdout + proc.stderr
    doc = report(tmp_path / "run")
    truth = json.loads((REPO / "recipes" / "parts" / "pillar_actual.truth.json").read_text())
    assert doc["verdict"] == "fail"
    dent = doc["regions"][0]
    assert dent["kind"] == "dent"
    assert np.linalg.norm(np.subtract(dent["centre_mm"], truth["centre_mm"])) < 2.0
    assert abs(dent["extreme_mm"] - truth["signed_deviation_mm"]) < 0.05
    assert doc["coverage"] >= 0.95
    # nothing else fails: every other out-of-tolerance cluster would be a false alarm
    assert len(doc["regions"]) == 1
    assert "verdict: FAIL" in proc.stdout
    # the earlier views' cut and merge made ahead of the last view: taken only where the last view left their
    # corrections as they were (it is held), else the registration merged all views in full
    journal = [json.loads(line) for line in (tmp_path / "run" / "journal.jsonl").read_text().splitlines()]
    made = [e for e in journal if e["event"] == "merge_ahead"]
    registration = [e for e in journal if e["event"] == "registration"][-1]
    views = registration["views"]
    assert made and made[-1]["views"] == views - 1
    assert made[-1]["used"] == (views - 1 in registration["refinement"]["unregistered_views"]), made[-1]


@pytest.fixture(scope="module")
def box_reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A small box recipe and a cell config with the 160x120 test sensor, written as files for the CLI, and
    the run folder of their uninterrupted `cell inspect` (a `python -m cell` process), made once per test
    session for this file and tests/test_controller_safety.py (tests/shared_runs.py).

    The box stands where the robot reaches all its faces: a run takes about 8 s on the shared 2-core machine,
    against 37 s at the origin, where the planner splits the unreachable face into tiny patches."""
    return box_cli_reference(tmp_path_factory)


# the journal lines of the run's steps: a view captured, a view measured, the evaluation, the report...; not
# the lines each process writes as it starts or resumes the run (lock, resuming, connecting, homing)
STEPS = re.compile(
    rb'^.*"event": "(?:plan|capture|view|evaluation|replan|registration|verdict|report_written)".*$', re.M
)


def _progress(run: Path) -> int:
    """The steps the run has done (:data:`STEPS`: a line's event and view), each counted once however often
    it was redone after a kill; -1 while the run folder does not exist under its name."""
    path = run / "journal.jsonl"
    if not path.exists():
        return -1
    steps = set()
    for line in STEPS.findall(path.read_bytes()):
        try:
            entry = json.loads(line)
        except ValueError:  # the line being written
            continue
        steps.add((entry["event"], entry.get("view")))
    return len(steps)


def _finished(run: Path) -> bool:
    checkpoint = run / "checkpoint.json"
    return (run / "results" / "report.json").exists() and (
        checkpoint.exists() and json.loads(checkpoint.read_text()).get("phase") == "done"
    )


JUDGED = (ExitCode.PASS, ExitCode.FAIL, ExitCode.INCOMPLETE)  # a finished run exits with its verdict
KILLS = 20
KILLS_PER_CHAIN = 10


@pytest.fixture(scope="module")
def cli_forks() -> Iterator[None]:
    """The forkserver the killed processes are forked from (tests/cli_process.py), for this module's tests."""
    with cli_process.server():
        yield


def _partial(run: Path, pid: int | None) -> bool:
    """Whether process ``pid``'s `cell inspect` has made its partial run folder (its inputs being copied)."""
    return (run.parent / f".{run.name}.partial-{pid}").exists()


@pytest.mark.timeout(900)  # 20 kills in 2 chains of kill, resume, kill... of the box run, on a shared machine
def test_killed_runs_resume_to_the_same_result(
    box_reference: tuple[Path, Path, Path], cli_forks: None, tmp_path: Path
) -> None:
    """SIGKILL (no handler runs) at 20 points spread over the run, then `cell resume` ends with the result of
    an uninterrupted run. The kills come in 2 chains of 10: each chain starts a `cell inspect`, kills it,
    resumes, kills the resume, ... and finally lets a resume finish, whose report is compared with the
    uninterrupted run's (once per chain). The first two processes of a chain are killed during start-up: the
    first once it has made its partial run folder (inputs being copied, the lock being taken), the second by
    time (the run folder may not exist yet, or hold a dead process's lock); the other eight at steps spread
    over the reference run's (views captured and measured, evaluation, replanning, registration, report, as
    its journal records them: the run's own progress, not a wall-clock guess), each once the process has
    done a step of its own.

    The uninterrupted run is a `python -m cell` process; the killed ones and the resumes run the same entry
    point (`cell.cli.main`) in processes forked from one that has imported it (tests/cli_process.py), so the
    21 of them pay the interpreter's ~3 s of imports once (a kill during the imports would leave nothing)."""
    recipe, cell_file, ref = box_reference
    expected = report(ref)  # its exit code checked against its verdict when it was made
    n_ref = _progress(ref)
    inspect = ["inspect", str(recipe), "--cell", str(cell_file), "--out"]
    rng = np.random.default_rng(7)
    kills, chain = 0, 0
    while kills < KILLS:
        assert chain < 2 * KILLS // KILLS_PER_CHAIN, f"only {kills} kills landed before their runs ended"
        run = tmp_path / f"c{chain}"
        # kill points: two in start-up, then steps spread over the reference run's
        targets = [-1, 0, *np.sort(rng.integers(1, n_ref, size=KILLS_PER_CHAIN - 2))]
        for j, target in enumerate(targets):
            if kills == KILLS or _finished(run):
                break
            args = ["resume", str(run)] if run.exists() else [*inspect, str(run)]
            context = f"chain {chain} kill {j} ({args[0]}, step {target})"
            start = _progress(run)
            proc = cli_process.start(args, tmp_path / f"c{chain}-{j}.log")
            if target == -1:  # start-up: its partial run folder made (inputs being copied), a little later
                while proc.is_alive() and not _partial(run, proc.pid) and not run.exists():
                    time.sleep(0.002)
                time.sleep(rng.uniform(0.0, 0.05))
            elif target == 0:  # start-up: loading inputs, copying them or taking over a dead process's lock
                time.sleep(rng.uniform(0.0, 0.5))
            else:  # once this process has done a step and the run has reached the target, a little later
                while proc.is_alive() and _progress(run) < max(target, start + 1):
                    time.sleep(0.005)
                time.sleep(rng.uniform(0.0, 0.3))
            if proc.is_alive():
                proc.kill()
                kills += 1
            proc.join(timeout=60)
            assert proc.exitcode in (*JUDGED, -signal.SIGKILL), context
        if not _finished(run):
            args = ["resume", str(run)] if run.exists() else [*inspect, str(run)]
            judged_report(cli_process.run(args, tmp_path / f"c{chain}-end.log"), run)
        assert_same_result(report(run), expected, f"chain {chain}")
        chain += 1
    assert kills == KILLS


class _SetAfter(threading.Event):
    """A stop event that reads as set from its ``checks + 1``-th look on (a registration called off then)."""

    def __init__(self, checks: int) -> None:
        super().__init__()
        self.checks = checks

    def is_set(self) -> bool:
        self.checks -= 1
        return self.checks < 0


def _registered(run_path: Path, bins: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The box run's registration (points, deviations, u) in a new job, its views' merge bins made as the
    decode worker makes them (``eager``: all but the plan's last view, as they arrive), when the registration
    first asks for them (``lazy``: a resumed run), with none kept (``none``: a budget of 0 bytes), or
    (``redo``) eagerly, with the last view that has points first binned from other points (a first decode of
    it), then decoded again as the plan's last view is (its bins left to the registration); ``done``: lazy,
    with the caches of the evaluations (the refinement's overlaps and the maps' pairs the decodes made)
    dropped by :meth:`LambertianInspection.evaluations_done` before the registration, as the controller
    drops them after the last evaluation (the maps' pairs found again equal those dropped); ``called_off``:
    eager, with a first registration called off midway, between views' bins (:class:`cell.errors.CalledOff`,
    as the controller calls off one begun beside an evaluation that asks for more views), then all views but
    the last cut and merged ahead from the refinement's corrections (:meth:`InspectionResults.merge_ahead`;
    one made first is voided by a view forgotten), which the registration finishes with the last view."""
    from cell.analysis.merge import bin_view
    from cell.inspection import LambertianInspection
    from cell.inspection_run import load_run_inputs, open_inspection_run
    from cell.mesh import load_mesh
    from cell.planning.feedback import MAP_LINK_MM
    from cell.run_data import Checkpoint

    run = open_inspection_run(run_path)
    recipe, cfg, _ = load_run_inputs(run)
    job = LambertianInspection(
        recipe, cfg, load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
    )
    state = job.merge_bins_for(run)
    if bins == "none":
        state.kept_bytes = 0
    done = run.completed_views()
    last = done[-1]
    if bins == "redo":  # the first decode's points 30 mm off (binned as the decode worker bins them)
        last = max(i for i in done if len(job.views.get(run, i).eval_W))
        first, n = job._view_bins(job.views.get(run, last))
        state.add(last, bin_view(first.mean + [30.0, 0, 0], first.weight, None, state.voxel_mm), n)
    for i in done:
        view = job.views.get(run, i)
        job._first_overlaps(run, view, pair_maps=i != last)
        if bins in ("eager", "redo", "called_off") and i != last:
            job.bin_arrived_view(run, view)
    if bins == "done":
        n = len(done)

        def map_pairs() -> list[np.ndarray]:  # at the maps' link and at 5 mm (the box's views overlap little)
            pairs = job._map_pairs(run, done)
            ab = [(a, b) for a in range(n) for b in range(n) if a != b]
            return [p for a, b in ab for link in (MAP_LINK_MM, 5.0) for p in pairs(a, b, link)]

        held = map_pairs()
        assert job._overlaps._first  # what the registration's refinement would otherwise begin with
        job.evaluations_done()
        assert not job._overlaps._first and not job._pairs._pairs
        again = map_pairs()
        assert any(map(len, held))
        assert all(a.tobytes() == b.tobytes() for a, b in zip(held, again, strict=True))
    views = Checkpoint.from_json(run.load_checkpoint()).views
    made_ahead = None
    if bins == "called_off":
        stop = _SetAfter(checks=4)  # passes the refinement's check and some views' bins, then stops
        with pytest.raises(CalledOff):
            job.register(run, views, stop=stop)
        assert stop.checks < 0 and job._cloud is None  # stopped where asked, nothing of it kept
        assert not state._merging  # the bins it made while merging are dropped, as after a whole merge
        # all views but the last cut and merged ahead with their refinement's corrections
        order, refined = job.refinement(run)
        before = [k for k in refined.unregistered if k < len(order) - 1]
        assert job.merge_ahead(run, order[:-1], refined.T[:-1], before)
        state.forget(order[0])  # one of its views measured again voids it
        assert state.take_ahead() is None
        job.bin_arrived_view(run, job.views.get(run, order[0]))
        assert job.merge_ahead(run, order[:-1], refined.T[:-1], before)
        state.forget(order[-1])  # (as the last view's decode begins: it stays)
        made_ahead = state._ahead
        assert made_ahead is not None and made_ahead.nbytes > 0
    job.register(run, views)
    if bins == "called_off":  # the registration finished it with the last view, and dropped it
        assert made_ahead is not None and made_ahead.merge.used and state._ahead is None
    cloud = job._cloud
    assert cloud is not None and cloud.error_map is not None and cloud.uncertainty_mm is not None
    return cloud.points_P, cloud.error_map.deviation_mm, cloud.uncertainty_mm


def test_the_ways_of_making_merge_bins_register_the_same_cloud(
    box_reference: tuple[Path, Path, Path],
) -> None:
    """Bins made as the views arrive, on first ask (a resumed run), with none kept, or of the plan's last view
    decoded again after a first decode had binned it: the same registered cloud, byte for byte; also when the
    evaluations' caches were dropped before the registration (its refinement then makes the views' overlaps
    anew), and after a registration called off midway, with the earlier views' cut and merge then made ahead
    of the last view (InspectionResults.merge_ahead) and finished with it."""
    want = _registered(box_reference[2], "lazy")
    assert len(want[0]) > 1000
    for bins in ("none", "redo", "done", "called_off"):  # (redo: eager, the last view's first bins forgotten)
        got = _registered(box_reference[2], bins)
        for a, b in zip(got, want, strict=True):
            assert a.tobytes() == b.tobytes(), bins
