"""The verification history and its drift warning; `cell verify check` end to end (binned simulated cell)."""

from __future__ import annotations

import json

import pytest

from cell.cli import main
from cell.verification.history import Entry, VerificationHistory, drift_warnings
from cell.verification.procedure import AcceptanceResult

MPE = {"PF": 0.05, "PS": 0.05, "SD": 0.025, "F": 0.05}


def _entries(sd_values: list[float]) -> list[Entry]:
    return [
        Entry(
            f"2026-11-{i + 1:02d}T06:00:00+00:00",
            "check",
            f"/r/{i}",
            "c",
            {"PF": 0.01, "PS": 0.0, "SD": v, "F": 0.01},
            "pass",
        )
        for i, v in enumerate(sd_values)
    ]


def test_steady_figures_do_not_warn() -> None:
    assert drift_warnings(_entries([0.005, 0.006, 0.005, 0.006]), MPE) == []


def test_slow_drift_warns_before_the_limit() -> None:
    # +2.5 um a day from 2.5 um: 10 um today, the 25 um MPE six checks away -> no warning yet; one day later
    # it is five checks away -> warned, while the value (12.5 um) is still only half the MPE
    series = [0.0025, 0.005, 0.0075, 0.010]
    assert drift_warnings(_entries(series), MPE) == []
    warned = drift_warnings(_entries([*series, 0.0125]), MPE)
    assert len(warned) == 1 and warned[0].startswith("SD drifts")


def test_share_of_mpe_and_excess_warn() -> None:
    assert "uses 80%" in drift_warnings(_entries([0.02]), MPE)[0]
    assert "exceeds" in drift_warnings(_entries([-0.03]), MPE)[0]  # size errors count by magnitude


def test_history_round_trip(tmp_path) -> None:
    h = VerificationHistory(tmp_path)
    r = AcceptanceResult(
        "cell-a",
        "nominal",
        {},
        MPE,
        [],
        figures_mm={"PF": 0.01, "PS": None, "SD": 0.002, "F": 0.02},
        verdict="pass",
    )
    h.add(tmp_path / "b", "check", r, time="2026-11-02T06:00:00+00:00")
    h.add(tmp_path / "a", "acceptance", r, time="2026-11-01T06:00:00+00:00")
    got = h.entries("cell-a")
    assert [e.kind for e in got] == ["acceptance", "check"] and got[1].figures_mm["PS"] is None
    assert h.entries("other") == []


def test_check_command_stores_its_figures(tmp_path, capsys) -> None:
    try:  # exit code 1 when a figure exceeds its MPE (the binned camera's noise floor exceeds PF's)
        main(["verify", "check", "--cell", "recipes/cells/sim_binned.yaml", "--runs", str(tmp_path)])
    except SystemExit as exc:
        assert exc.code == 1
    out = capsys.readouterr().out
    assert "check:" in out
    folders = list(tmp_path.glob("verify-check-*"))
    assert len(folders) == 1
    doc = json.loads((folders[0] / "verification.json").read_text())
    assert [p["label"] for p in doc["positions"]] == ["ball bar, space diagonal 1", "plane, flat middle"]
    assert all(v is not None for v in doc["figures_mm"].values())
    (entry,) = VerificationHistory(tmp_path).entries()
    assert entry.kind == "check" and entry.figures_mm["SD"] == pytest.approx(doc["figures_mm"]["SD"])
    assert (folders[0] / "inputs" / "certificate.yaml").is_file()
    main(["verify", "history", "--runs", str(tmp_path)])
    said, header, row = capsys.readouterr().out.splitlines()  # what it reads, then the table
    assert said == f"interim checks in {tmp_path / 'results.sqlite'}, oldest first"
    assert header.startswith("time") and "check" in row


def test_a_failed_check_blocks_inspections_until_one_passes(tmp_path) -> None:
    """`cell inspect` refuses to start a run of a cell whose newest verification in the runs root failed,
    naming the figures and how to clear it; a later passing check (or the config switch) lets it start."""
    from pathlib import Path

    import yaml

    from cell.config import load_cell_config
    from cell.errors import ConfigError
    from cell.inspection_run import start_run

    repo = Path(__file__).resolve().parent.parent
    cell = repo / "recipes" / "cells" / "sim_binned.yaml"
    recipe = repo / "recipes" / "pillar.yaml"
    name = load_cell_config(cell).name
    failed = AcceptanceResult(
        name,
        "nominal",
        {},
        MPE,
        [],
        figures_mm={"PF": 0.01, "PS": 0.002, "SD": 0.031, "F": 0.02},
        verdict="fail",
    )
    history = VerificationHistory(tmp_path)
    history.add(tmp_path / "check-1", "check", failed, time="2026-11-02T06:00:00+00:00")
    with pytest.raises(
        ConfigError, match=r"failed its last verification \(check.*SD 31.0 um.*cell verify check"
    ):
        start_run(recipe, cell, tmp_path / "run-1", None)
    assert not (tmp_path / "run-1").exists()  # refused before anything was written

    data = yaml.safe_load(cell.read_text())
    data.setdefault("verification", {})["block_inspections"] = False
    unblocked = tmp_path / "unblocked.yaml"
    unblocked.write_text(yaml.safe_dump(data))
    assert start_run(recipe, unblocked, tmp_path / "run-2", None).path.is_dir()

    passed = AcceptanceResult(
        name, "nominal", {}, MPE, [], figures_mm=dict(failed.figures_mm), verdict="pass"
    )
    history.add(tmp_path / "check-2", "check", passed, time="2026-11-02T07:00:00+00:00")
    assert start_run(recipe, cell, tmp_path / "run-3", None).path.is_dir()
