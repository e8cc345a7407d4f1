"""Retention of raw view images (cell.retention, `cell prune`) on synthetic run folders whose finishing times
are set in their journals: what goes and what stays, dry runs, running and unfinished runs, the journal."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from cell.config import load_cell_config
from cell.errors import ConfigError
from cell.inspection_run import REPO
from cell.retention import DAY_S, RetentionConfig, prune
from cell.runs import RunFolder, process_start

NOW = 1_800_000_000.0  # a fixed "now" (UNIX time): ages are exact


def make_run(
    root: Path,
    name: str,
    *,
    verdict: str | None = "pass",
    phase: str = "done",
    age_days: float = 10.0,
    retention: dict | None = None,
    views: int = 2,
) -> Path:
    """A finished (or not) inspection run folder as a run leaves it: inputs with its cell config (and its
    ``retention:`` section), a journal whose ``done`` lies ``age_days`` before NOW, a checkpoint with the
    verdict, results, decoded views and each view's raw/ folder of frames."""
    run = root / name
    (run / "inputs").mkdir(parents=True)
    cell = {"name": "synthetic", **({"retention": retention} if retention is not None else {})}
    (run / "inputs" / "cell.yaml").write_text(yaml.safe_dump(cell))
    (run / "inputs" / "manifest.json").write_text(json.dumps({"recipe": "recipe.yaml", "cell": "cell.yaml"}))
    t_done = NOW - age_days * DAY_S
    entries = [
        {"t": t_done - 300, "event": "run_created"},
        {"t": t_done - 200, "event": "state", "state": "scanning"},
    ]
    if phase == "done":
        entries.append({"t": t_done, "event": "state", "state": "done"})
    (run / "journal.jsonl").write_text("".join(json.dumps(e) + "\n" for e in entries))
    (run / "checkpoint.json").write_text(
        json.dumps({"phase": phase, "views": [], "summary": {"verdict": verdict}})
    )
    (run / "results").mkdir()
    (run / "results" / "report.json").write_text(json.dumps({"verdict": verdict}))
    for i in range(views):
        v = run / "views" / f"{i:03d}"
        (v / "raw" / "frames").mkdir(parents=True)
        (v / "points.npz").write_bytes(b"p" * 100)
        (v / "view.json").write_text("{}")
        (v / "raw" / "capture.yaml").write_text("version: 1\n")
        for k in range(3):
            (v / "raw" / "frames" / f"{k}_f.png").write_bytes(b"x" * 1000)
    return run


RAW_PER_RUN = 2 * (3 * 1000 + len("version: 1\n"))


def _tree(root: Path, files_only: bool = False) -> dict[str, tuple[int, float]]:
    """Every path under ``root`` (files only: without folders, whose times change as entries go) with its
    size and modification time."""
    return {
        str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime)
        for p in sorted(root.rglob("*"))
        if not (files_only and p.is_dir())
    }


def _raw(run: Path) -> list[Path]:
    return sorted(run.glob("views/*/raw"))


def test_defaults_drop_passed_raw_images_and_keep_failed_ones_30_days():
    policy = RetentionConfig()
    assert policy.keep_days("pass") == 0 and policy.keep_days("fail") == 30
    assert policy.keep_days("incomplete") == 30 and policy.keep_days(None) == 30
    assert policy.writes_raw_images
    assert not RetentionConfig(raw_images_passed_days=0, raw_images_failed_days=0).writes_raw_images


def test_prune_removes_only_the_raw_images_its_policy_no_longer_keeps(tmp_path):
    policy = {"raw_images_passed_days": 7, "raw_images_failed_days": 30}
    old_pass = make_run(tmp_path, "old-pass", age_days=8, retention=policy)
    new_pass = make_run(tmp_path, "new-pass", age_days=6, retention=policy)
    young_fail = make_run(tmp_path, "young-fail", verdict="fail", age_days=29, retention=policy)
    old_incomplete = make_run(tmp_path, "old-incomplete", verdict="incomplete", age_days=31, retention=policy)
    forever = make_run(
        tmp_path, "forever", verdict="fail", age_days=3000, retention={"raw_images_failed_days": None}
    )
    before = {run: _tree(run, files_only=True) for run in (old_pass, old_incomplete)}
    report = prune(tmp_path, now=NOW)
    assert report.freed_bytes == 2 * RAW_PER_RUN
    assert {r.run.name for r in report.runs if r.action == "delete"} == {"old-pass", "old-incomplete"}
    for run in (old_pass, old_incomplete):
        assert _raw(run) == [] and not list(run.glob("views/*/.raw.pruning"))
        # everything else is as it was: results, inputs, checkpoint, decoded views (the journal grew)
        after = _tree(run, files_only=True)
        kept = {k: v for k, v in before[run].items() if "raw" not in k.split("/") and k != "journal.jsonl"}
        assert {k: after[k] for k in kept} == kept
        entry = json.loads((run / "journal.jsonl").read_text().splitlines()[-1])
        assert entry["event"] == "prune" and entry["freed_bytes"] == RAW_PER_RUN
        assert entry["removed"] == ["views/000/raw", "views/001/raw"]
    for run in (new_pass, young_fail, forever):
        assert len(_raw(run)) == 2
    # a second prune finds nothing more to do
    assert prune(tmp_path, now=NOW).freed_bytes == 0


def test_dry_run_touches_nothing_and_says_what_it_would_free(tmp_path):
    make_run(tmp_path, "a", age_days=40, verdict="fail")
    make_run(tmp_path, "b", age_days=1, verdict="pass")
    before = _tree(tmp_path)
    report = prune(tmp_path, dry_run=True, now=NOW)
    assert _tree(tmp_path) == before
    assert report.to_free_bytes == 2 * RAW_PER_RUN and report.freed_bytes == 0


def test_a_torn_journal_line_is_left_to_a_dry_run_and_cut_before_the_prune_entry(tmp_path):
    """A dry run reads a run whose last journal line is torn (a process died writing it; in a running run,
    the line being written) without cutting it; a prune, under the lock, cuts it so its entry parses."""
    run = make_run(tmp_path, "torn", verdict="fail", age_days=40)
    with open(run / "journal.jsonl", "a") as f:
        f.write('{"t": 1, "event": "sta')
    before = (run / "journal.jsonl").read_bytes()
    prune(tmp_path, dry_run=True, now=NOW)
    assert (run / "journal.jsonl").read_bytes() == before
    prune(tmp_path, now=NOW)
    entries = RunFolder.open(run).journal()
    assert entries[-1]["event"] == "prune" and entries[-2]["state"] == "done"


def test_unfinished_runs_are_never_pruned_however_old(tmp_path):
    """A run not done can still be resumed: its views (raw images included) stay."""
    run = make_run(tmp_path, "paused", phase="scanning", verdict=None, age_days=10_000)
    before = _tree(tmp_path)
    report = prune(tmp_path, RetentionConfig(raw_images_passed_days=0, raw_images_failed_days=0), now=NOW)
    assert _tree(tmp_path) == before
    (entry,) = report.runs
    assert entry.action == "skip" and "resumed" in entry.reason and len(_raw(run)) == 2


def test_a_run_in_use_is_skipped(tmp_path):
    """A live process holds the run's lock (another process, as `cell report` or `cell resume` would)."""
    run = make_run(tmp_path, "busy", verdict="fail", age_days=400)
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = {
            "pid": holder.pid,
            "host": socket.gethostname(),
            "start": process_start(holder.pid),
            "command": "x",
        }
        (run / "run.lock").write_text(json.dumps(lock))
        before = _tree(tmp_path)
        (entry,) = prune(tmp_path, now=NOW).runs
        assert entry.action == "skip" and f"PID {holder.pid}" in entry.reason
        assert _tree(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()
    # once that process is gone its lock is stale: the next prune takes it over and prunes
    (entry,) = prune(tmp_path, now=NOW).runs
    assert entry.action == "delete" and _raw(run) == [] and not (run / "run.lock").exists()


def test_a_cell_config_policy_overrides_each_runs_own(tmp_path):
    run = make_run(tmp_path, "r", verdict="fail", age_days=20, retention={"raw_images_failed_days": None})
    assert prune(tmp_path, now=NOW).freed_bytes == 0  # its own policy: for ever
    report = prune(tmp_path, RetentionConfig(raw_images_failed_days=14), now=NOW)
    assert report.freed_bytes == RAW_PER_RUN and _raw(run) == []


def test_age_is_read_from_the_journal_not_from_file_times(tmp_path):
    """A runs root restored from a backup has new file times; the journal keeps when the run finished."""
    run = make_run(tmp_path, "restored", verdict="fail", age_days=45)
    now_s = time.time()
    for p in run.rglob("*"):
        os.utime(p, (now_s, now_s))
    (entry,) = prune(tmp_path, now=NOW).runs
    assert entry.action == "delete" and "45.0 days" in entry.reason


def test_a_prune_killed_midway_is_finished_by_the_next(tmp_path):
    """A raw folder renamed aside but not yet deleted (the process died) is removed by the next prune."""
    run = make_run(tmp_path, "half", verdict="fail", age_days=40)
    (run / "views" / "000" / "raw").rename(run / "views" / "000" / ".raw.pruning")
    report = prune(tmp_path, now=NOW)
    assert report.freed_bytes == RAW_PER_RUN
    assert not list(run.glob("views/*/.raw*")) and not list(run.glob("views/*/raw"))


def test_other_folders_and_a_missing_root(tmp_path):
    """Calibration runs, hidden folders of runs being created and stray files are not inspection runs."""
    make_run(tmp_path, ".pillar.partial-123", verdict="fail", age_days=99)
    calib = RunFolder.create(tmp_path, "calib", name="calibration-x")
    calib.mark_kind("calibration")
    calib.log("state", state="done")
    (tmp_path / "index.sqlite").write_bytes(b"")
    assert prune(tmp_path, now=NOW).runs == []
    with pytest.raises(ConfigError, match="runs root not found"):
        prune(tmp_path / "nope")


def test_a_bad_retention_section_is_refused_naming_the_field(tmp_path):
    data = yaml.safe_load((REPO / "recipes" / "cells" / "sim_binned.yaml").read_text())
    for bad, field in (({"raw_images_passed_days": -1}, "raw_images_passed_days"), ({"keep": 3}, "keep")):
        path = tmp_path / "cell.yaml"
        path.write_text(yaml.safe_dump({**data, "retention": bad}))
        with pytest.raises(ConfigError) as exc:
            load_cell_config(path)
        assert exc.value.field == f"retention.{field}" and str(path) in str(exc.value)
    # a run whose own cell config has a bad section is left alone, with the reason
    run = make_run(
        tmp_path / "runs", "r", verdict="fail", age_days=400, retention={"raw_images_failed_days": "x"}
    )
    (entry,) = prune(tmp_path / "runs", now=NOW).runs
    assert entry.action == "skip" and "retention" in entry.reason and len(_raw(run)) == 2


def test_cell_prune_command(tmp_path):
    """The command in process (typer's runner) for its output, and once as a process for the exit code."""
    from typer.testing import CliRunner

    from cell.cli import app

    make_run(tmp_path, "old", verdict="fail", age_days=400)

    def prune_cmd(*args: str) -> str:
        result = CliRunner().invoke(app, ["prune", "--runs", str(tmp_path), *args])
        assert result.exit_code == 0, result.output
        return result.output

    assert "would remove" in prune_cmd("--dry-run") and len(_raw(tmp_path / "old")) == 2
    cell = tmp_path.parent / "policy.yaml"
    data = yaml.safe_load((REPO / "recipes" / "cells" / "sim_binned.yaml").read_text())
    cell.write_text(yaml.safe_dump({**data, "retention": {"raw_images_failed_days": None}}))
    assert "removed 0.0 MB" in prune_cmd("--cell", str(cell)) and len(_raw(tmp_path / "old")) == 2
    assert f"removed {RAW_PER_RUN / 1e6:.1f} MB" in prune_cmd() and _raw(tmp_path / "old") == []
    bad = subprocess.run(
        [sys.executable, "-m", "cell", "prune", "--runs", str(tmp_path / "none")],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "runs root not found" in bad.stderr
