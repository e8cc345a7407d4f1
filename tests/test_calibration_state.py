"""The calibration state a run records (cell/calibration_state.py): files, age, the cell config they were made
for, quality; with ``requires_calibration`` a missing, stale or poor calibration makes the verdict
incomplete, naming why."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from cell.analysis.report import ReportInput, Tolerance, summarise
from cell.calibration.store import save_calibration
from cell.calibration_state import calibration_state
from cell.config import DEFAULT_CELL, CellConfig, config_fingerprint, load_cell_config


def _calibrated(tmp_path: Path, **meta_by_field: dict) -> CellConfig:
    """The default cell with calibration files written by the store, metadata per field."""
    cfg = load_cell_config(DEFAULT_CELL)
    kinds = {"intrinsics": "camera_intrinsics", "projector": "projector", "hand_eye": "hand_eye"}
    paths = {}
    for field, meta in meta_by_field.items():
        paths[field] = save_calibration(tmp_path / field, kinds[field], {"x": np.zeros(1)}, meta)
    return cfg.model_copy(update={"calibration": cfg.calibration.model_copy(update=paths)})


def test_fingerprint_ignores_the_calibration_section_and_sees_the_rest(tmp_path: Path) -> None:
    cfg = load_cell_config(DEFAULT_CELL)
    with_files = _calibrated(tmp_path, hand_eye={})
    assert config_fingerprint(with_files) == config_fingerprint(cfg)
    moved = cfg.model_copy(update={"sensor": cfg.sensor.model_copy(update={"standoff_mm": 400.0})})
    assert config_fingerprint(moved) != config_fingerprint(cfg)
    # the pose prior of the per-point uncertainty is set from the cell's validation, after its calibration
    prior = cfg.robot.model_copy(update={"pose_uncertainty_mm": 0.07, "pose_uncertainty_deg": 0.03})
    assert config_fingerprint(cfg.model_copy(update={"robot": prior})) == config_fingerprint(cfg)
    slower = cfg.robot.model_copy(update={"max_tcp_speed_mm_s": cfg.robot.max_tcp_speed_mm_s / 2})
    assert config_fingerprint(cfg.model_copy(update={"robot": slower})) != config_fingerprint(cfg)


def test_good_current_calibration_satisfies_a_recipe_that_requires_it(tmp_path: Path) -> None:
    fp = config_fingerprint(load_cell_config(DEFAULT_CELL))
    cfg = _calibrated(
        tmp_path,
        intrinsics={"cell_config_sha256": fp, "quality": {"rms_px": 0.2}},
        projector={"cell_config_sha256": fp, "quality": {"rms_px": 0.4}},
        hand_eye={"cell_config_sha256": fp, "quality": {"rms_mm": 0.03}},
    )
    state = calibration_state(cfg, required=True, now=time.time() + 2 * 86400)
    assert state["incomplete_reasons"] == []
    assert [f["field"] for f in state["files"]] == ["hand_eye", "intrinsics", "projector"]
    for f in state["files"]:
        assert f["made_for_this_config"] is True and f["problems"] == []
        assert f["age_days"] == pytest.approx(2.0, abs=0.01) and f["age_from"] == "created_utc"
        assert f["created_utc"]


def test_missing_stale_unknown_or_poor_calibration_is_named(tmp_path: Path) -> None:
    cfg = _calibrated(
        tmp_path,
        intrinsics={"cell_config_sha256": "0" * 64, "quality": {"rms_px": 0.2}},  # made for another config
        projector={"quality": {"rms_px": 0.4}},  # no fingerprint: cannot tell
    )
    state = calibration_state(cfg, required=True)
    reasons = " | ".join(state["incomplete_reasons"])
    assert "intrinsics: intrinsics.yaml is stale" in reasons
    assert "projector: projector.yaml records no cell_config_sha256" in reasons
    assert "no hand-eye calibration" in reasons
    fp = config_fingerprint(load_cell_config(DEFAULT_CELL))
    poor = _calibrated(
        tmp_path / "poor",
        intrinsics={"cell_config_sha256": fp, "quality": {"rms_px": 2.5}},
        projector={"cell_config_sha256": fp, "quality": {"rms_px": 0.3, "acceptable": False}},
        hand_eye={"cell_config_sha256": fp, "quality": {"rms_mm": 0.5}},
    )
    reasons = " | ".join(calibration_state(poor, required=True)["incomplete_reasons"])
    assert "quality.rms_px = 2.5 > 1.0" in reasons and "quality.rms_mm = 0.5 > 0.1" in reasons
    assert "marked not acceptable" in reasons
    # not required: the files and their problems are recorded, the verdict is not touched
    relaxed = calibration_state(poor, required=False)
    assert relaxed["incomplete_reasons"] == [] and relaxed["files"][0]["problems"]
    none = calibration_state(load_cell_config(DEFAULT_CELL), required=True)
    assert any("no intrinsics and no projector calibration" in r for r in none["incomplete_reasons"])


def test_incomplete_reasons_turn_pass_and_fail_into_incomplete() -> None:
    pts = np.random.default_rng(0).uniform(0, 10, (500, 3))
    for dev, plain in ((np.zeros(500), "pass"), (np.full(500, 1.0), "fail")):
        inp = ReportInput(pts, dev, Tolerance(-0.1, 0.1), 500)
        assert summarise(inp)["verdict"] == plain
        inp.incomplete_reasons = ["the recipe requires calibration; the cell has no hand-eye calibration"]
        doc = summarise(inp)
        assert doc["verdict"] == "incomplete" and doc["incomplete_reasons"] == inp.incomplete_reasons
