"""Run folders: atomic views, torn journal lines, checkpoints and the SQLite index."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cell.errors import ConfigError
from cell.runs import RunFolder


def test_view_exists_whole_or_not_at_all(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path, "part", name="r1")
    with run.writing_view(0) as d:
        np.save(d / "points.npy", np.ones((10, 3)))
    with pytest.raises(RuntimeError):
        with run.writing_view(1) as d:
            np.save(d / "points.npy", np.ones((10, 3)))
            raise RuntimeError("killed mid-write")
    assert run.completed_views() == [0]
    assert np.load(run.view_dir(0) / "points.npy").shape == (10, 3)
    assert not [p for p in (run.path / "views").iterdir() if p.name.startswith(".")]


def test_partial_view_folders_left_by_a_kill_are_discarded(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path, "part", name="r1")
    (run.path / "views" / ".003.abc").mkdir()  # what a SIGKILL during writing_view leaves behind
    assert run.completed_views() == []
    run.discard_partial_views()
    assert list((run.path / "views").iterdir()) == []


def test_torn_journal_line_is_skipped(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path, "part", name="r1")
    run.log("state", state="connecting")
    run.log("view", view=0, pose=np.eye(4))
    with open(run.journal_path, "a") as f:
        f.write('{"t": 1, "event": "vi')  # the process died mid-write
    entries = run.journal()
    assert [e["event"] for e in entries] == ["state", "view"]
    assert entries[1]["pose"] == np.eye(4).tolist()
    reopened = RunFolder.open(run.path)  # what `cell resume` does: the next entry must not be glued on
    reopened.log("state", state="resuming")
    assert [e["event"] for e in reopened.journal()] == ["state", "view", "state"]


def test_checkpoint_round_trip_and_reopen(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path, "part", name="r1")
    run.log("state", state="idle")
    run.save_checkpoint({"phase": "scanning", "views": [{"T_B_T": np.eye(4)}]})
    again = RunFolder.open(run.path)
    assert again.load_checkpoint()["views"][0]["T_B_T"] == np.eye(4).tolist()
    with pytest.raises(ConfigError, match="not a run folder"):
        RunFolder.open(tmp_path / "elsewhere")
    with pytest.raises(ConfigError, match="holds files already; choose another --out, or `cell resume`"):
        RunFolder.create(tmp_path, "part", name="r1")


def test_the_report_and_the_results_database_state_one_start(tmp_path: Path) -> None:
    """A run's start is its journal's run_created entry (before it: the first entry; no journal: the
    manifest's time), and the report's run record and the results database's row say the same time."""
    import json
    import os
    from datetime import UTC, datetime

    from cell.results.folder import read_run
    from cell.run_record import run_record

    run = RunFolder.create(tmp_path, "part", name="r1")
    manifest = run.path / "inputs" / "manifest.json"
    manifest.write_text("{}")
    os.utime(manifest, (1_600_000_000, 1_600_000_000))
    assert run.started() == datetime(2020, 9, 13, 12, 26, 40, tzinfo=UTC)  # no journal yet
    lines = [{"t": 1_700_000_000.25, "event": "state", "state": "idle"}]
    run.journal_path.write_text("".join(json.dumps(e) + "\n" for e in lines))
    assert run.started() == datetime(2023, 11, 14, 22, 13, 20, 250000, tzinfo=UTC)  # a folder from before
    lines.insert(1, {"t": 1_700_000_100.0, "event": "run_created", "part": "part"})
    run.journal_path.write_text("".join(json.dumps(e) + "\n" for e in lines) + '{"t": 1, "ev')  # torn
    created = datetime(2023, 11, 14, 22, 15, tzinfo=UTC)
    assert run.started() == created
    assert run_record(run)["started_utc"] == "2023-11-14T22:15:00+00:00"
    assert read_run(run.path).run["started"] == created
