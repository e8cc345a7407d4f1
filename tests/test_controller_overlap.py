# ruff: noqa: F811  (the fixtures recipe_path and reference come from tests/test_controller.py)
"""The work beside the robot (cell/controller.py's worker) and the verdict before the report's page, on the
small box cell: a view whose background work fails faults the run naming that view and loses nothing else;
a run that faults after its last view's decode keeps that view's raw images; the verdict is published
(report.json, the journal's verdict line, the checkpoint's summary) before the page is written, stands
against an abort, and a run paused between the two resumes to the uninterrupted result.

Truth: the uninterrupted reference run of tests/test_controller.py and the run folder's own files."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from cell.controller import abort_stopped
from cell.errors import ConfigError
from cell.inspection_views import load_view_result
from cell.run_data import Phase
from cell.runs import RunFolder
from cell.view_files import load_raw_stack
from tests.same_result import assert_same_result
from tests.test_controller import (  # noqa: F401
    keep_last_stacks,
    make_controller,
    recipe_path,
    reference,
    result_of,
)


def test_a_failing_view_faults_the_run_naming_it_and_a_resume_measures_it(
    recipe_path: Path, tmp_path: Path, reference: dict
) -> None:
    """A bug in view 2's work faults the run naming the view; the resume measures it and the views after
    it, and faults in ``registering`` (a registration with no points) after its last view's decode: that
    view's raw stack, held back for after the verdict, is written into its folder on the way out (a whole
    capture folder, read back equal to the captured stack); the next resume registers, writes nothing again,
    and ends with the uninterrupted run's result."""
    run_dir = tmp_path / "run"
    ctl, _ = make_controller(recipe_path, run_dir)
    decode = ctl.job.decode

    def decode_failing_at_view_2(view, captured, out_dir):  # a bug in the view's own work, in the worker
        if captured.index == 2:
            raise ValueError("injected failure")
        return decode(view, captured, out_dir)

    ctl.job.decode = decode_failing_at_view_2
    assert ctl.execute() == "faulted"
    assert ctl.message.startswith("view 2: its processing failed (ValueError: injected failure)")
    journal = ctl.run.journal()
    errors = [e for e in journal if e["event"] == "error" and e["kind"] == "ViewProcessingError"]
    assert len(errors) == 1 and "view 2" in errors[0]["error"]
    done = set(ctl.run.completed_views())
    assert {0, 1} <= done and 2 not in done  # the failed view is not counted as measured
    assert not (run_dir / "results" / "report.json").exists()
    ctl2, _ = make_controller(recipe_path, run_dir)
    kept = keep_last_stacks(ctl2)
    ctl2.job.register = lambda run, views, stop=None: {"n_points": 0}  # no points: the run faults
    assert ctl2.execute(resume=True) == "faulted", ctl2.message
    assert ctl2.message == "registration produced no points: nothing to report"
    assert done < set(ctl2.run.completed_views())
    last = len(ctl2.checkpoint.views) - 1
    assert ctl2.run.completed_views() == list(range(last + 1)) and last in kept
    assert (run_dir / "views" / f"{last:03d}" / "raw" / "capture.yaml").is_file()
    raw = load_raw_stack(ctl2.run.view_dir(last))
    assert raw is not None and raw.dtype == kept[last].dtype and np.array_equal(raw, kept[last])
    written = [e for e in ctl2.run.journal() if e["event"] == "written_on_stop"]
    assert len(written) == 1 and written[0]["view"] == last and written[0]["state"] == "faulted"
    ctl3, _ = make_controller(recipe_path, run_dir)
    assert ctl3.execute(resume=True) == "done", ctl3.message
    assert len([e for e in ctl3.run.journal() if e["event"] == "written_on_stop"]) == 1
    assert np.array_equal(load_raw_stack(ctl3.run.view_dir(last)), kept[last])
    assert_same_result(result_of(run_dir), reference["result"], "a view failed, then resumed")


def test_the_verdict_is_published_before_the_page_and_stands(
    recipe_path: Path, tmp_path: Path, reference: dict
) -> None:
    """A pause asked for right after the verdict: the run pauses in ``rendering`` with report.json and the
    verdict line written and no page; it cannot be aborted, and `resume` writes the page, same result."""
    run_dir = tmp_path / "run"
    ctl, _ = make_controller(recipe_path, run_dir)
    report = ctl.job.report

    def report_then_pause(run, registration):
        summary = report(run, registration)
        ctl.request_pause("test, right after the verdict")
        return summary

    ctl.job.report = report_then_pause
    assert ctl.execute() == "paused", ctl.message
    run = RunFolder.open(run_dir)
    # what the decode worker kept in memory is what the folders hold: a resumed run reads the same numbers
    for i in run.completed_views():
        kept, read = ctl.job.views.get(run, i), load_view_result(run.view_dir(i), i)
        assert kept.held is not None and kept.folder == run.view_dir(i)
        for a, b in [
            (kept.points().points_W, read.points().points_W),
            (kept.points().quality, read.points().quality),
            (kept.points().oblique, read.points().oblique),
            (kept.eval_W, read.eval_W),
            (kept.planes.centroid, read.planes.centroid),
            (kept.planes.normal, read.planes.normal),
            (kept.planes.ok, read.planes.ok),
        ]:
            assert a.dtype == b.dtype and np.array_equal(a, b)
        assert kept.summary == read.summary and len(kept.regions) == len(read.regions)
    journal = run.journal()
    states = [e["state"] for e in journal if e["event"] == "state"]
    assert states[-3:] == ["reporting", "rendering", "paused"]
    verdict = [e for e in journal if e["event"] == "verdict"]
    assert len(verdict) == 1 and verdict[0]["verdict"] == reference["result"]["verdict"]
    assert not [e for e in journal if e["event"] == "report_written"]
    results = sorted(p.name for p in (run_dir / "results").iterdir())
    assert results == ["report.json"]  # the verdict alone: no page, no cloud yet
    # the last view's raw stack, held for after the verdict, is not written on the way out: the published
    # verdict's retention keeps none (a passed part, raw_images_passed_days 0)
    assert reference["result"]["verdict"] == "pass"
    assert not (run.view_dir(len(ctl.checkpoint.views) - 1) / "raw").exists()
    assert not [e for e in journal if e["event"] in ("written_on_stop", "error")]
    checkpoint = run.load_checkpoint()
    assert (
        checkpoint["phase"] == Phase.RENDERING and checkpoint["summary"]["verdict"] == verdict[0]["verdict"]
    )
    doc = json.loads((run_dir / "results" / "report.json").read_text())
    assert doc["verdict"] == verdict[0]["verdict"] and doc["n_points"] == verdict[0]["n_points"]
    with pytest.raises(ConfigError, match="verdict is published and stands"):
        abort_stopped(run, "by the test")
    ctl2, _ = make_controller(recipe_path, run_dir)
    assert ctl2.execute(resume=True) == "done", ctl2.message
    journal = run.journal()
    assert [e["event"] for e in journal if e["event"] in ("verdict", "report_written")] == [
        "verdict",
        "report_written",
    ]
    assert sorted(p.name for p in (run_dir / "results").iterdir()) == [
        "cloud.ply",
        "report.html",
        "report.json",
    ]
    assert json.loads((run_dir / "results" / "report.json").read_text()) == doc  # the verdict as published
    assert_same_result(result_of(run_dir), reference["result"], "paused between verdict and page")


def test_captures_wait_when_the_views_work_falls_behind(
    recipe_path: Path, tmp_path: Path, reference: dict
) -> None:
    """A view's work slower than the robot and the camera (a loaded computer): a capture waits until at most
    one captured view waits for the worker, so the images held in memory stay bounded; same result."""
    ctl, _ = make_controller(recipe_path, tmp_path / "run")
    decode = ctl.job.decode

    def slow_decode(view, captured, out_dir):
        time.sleep(0.5)
        return decode(view, captured, out_dir)

    ctl.job.decode = slow_decode
    assert ctl.execute() == "done", ctl.message
    captured, worked, waiting = 0, 0, []
    for e in ctl.run.journal():
        if e["event"] == "capture":  # the views captured and not yet worked on, as this one starts
            waiting.append(captured - worked)
            captured += 1
        elif e["event"] == "view":
            worked += 1
    in_reference = [e for e in RunFolder.open(reference["run_dir"]).journal() if e["event"] == "capture"]
    assert max(waiting) <= ctl.settings.max_views_waiting and captured == len(in_reference)
    assert_same_result(result_of(ctl.run.path), reference["result"], "slow view work")
