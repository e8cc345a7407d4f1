"""The single-view acceptance procedure end to end in the simulated cell (binned camera for speed): the
simulated stage places the artefacts, the GCLS pipeline measures them, the figures are checked against the
certificate's truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.cli import main
from cell.config import load_cell_config
from cell.devices import build_artefact_stage, build_devices
from cell.verification.certificate import load_certificate
from cell.verification.procedure import AcceptanceResult, PositionResult, acceptance_positions, run_acceptance
from cell.verification.report import write_html, write_json

CELL = "recipes/cells/sim_binned.yaml"


def _run(world, labels):  # noqa: ANN001, ANN202
    cfg = load_cell_config(CELL)
    cfg.world = world
    cert = load_certificate()
    dev = build_devices(cfg)
    stage = build_artefact_stage(dev, cert)
    positions = [p for p in acceptance_positions(cfg, cert) if p.label in labels]
    placed = []
    place = stage.place

    def spy(artefact, T_W_A, label):  # noqa: ANN001, ANN202 - records the true placement
        place(artefact, T_W_A, label)
        placed.append((T_W_A, stage.placed_W.copy()))

    stage.place = spy
    result, clouds = run_acceptance(cfg, dev, stage, cert, positions=positions)
    return result, clouds, placed


def test_ideal_world_figures_are_a_noise_floor() -> None:
    result, clouds, placed = _run("ideal", {"ball bar, face diagonal 1", "plane, flat middle"})
    assert all(np.allclose(cmd, true) for cmd, true in placed)  # ideal: exactly where commanded
    bar, flat = result.positions
    assert bar.error is None and flat.error is None
    assert len(bar.pf_mm) == 2 and bar.n_points > 1000 and flat.n_points > 10000
    assert abs(bar.sd_mm) < 0.025
    assert all(abs(v) < 0.05 for v in bar.ps_mm)
    # no systematic form where the world is the model: F stays within the range of the noise (a Gaussian
    # would give about 6 RMS after the 0.3 % rule); binned pixels make the noise larger than the full camera's
    assert flat.f_mm < 7 * flat.rms_mm[0] and flat.rms_mm[0] < 0.03
    assert result.figures_mm["SD"] == bar.sd_mm and result.verdict in ("pass", "fail")


def test_honest_world_places_off_command_and_still_measures() -> None:
    result, _, placed = _run(None, {"ball bar, space diagonal 2"})
    cmd, true = placed[0]
    assert np.linalg.norm(cmd[:3, 3] - true[:3, 3]) > 0.5  # the technician's hand is off by the placement
    (bar,) = result.positions
    assert bar.error is None and len(bar.ps_mm) == 2
    # uncalibrated: sizes are off, but by a plausible amount (lens and baseline errors of the world)
    assert abs(bar.sd_mm) < 2.0 and all(abs(v) < 1.0 for v in bar.ps_mm)
    assert result.passed["F"] is None and result.verdict == "incomplete"  # no plane measured


def test_cli_refuses_a_non_empty_output_folder(tmp_path, capsys) -> None:
    (tmp_path / "x").write_text("keep me")
    with pytest.raises(SystemExit) as exc:
        main(["verify", "acceptance", "--cell", CELL, "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert (tmp_path / "x").read_text() == "keep me"
    assert "not empty" in capsys.readouterr().err


def test_report_escapes_every_user_string(tmp_path) -> None:
    cert = load_certificate()
    cert.plane.serial = "<script>alert(1)</script>"
    result = AcceptanceResult(
        cell="<b>cell</b>",
        geometry_source="nominal",
        volume_mm={"width": 200.0, "height": 150.0, "depth": 100.0, "L0": 269.0},
        mpe_mm={"PF": 0.05, "PS": 0.05, "SD": 0.025, "F": 0.05},
        positions=[PositionResult("<i>pos</i>", "plane", n_points=100, f_mm=0.01, error="<x>")],
    )
    result.summarise()
    write_html(tmp_path / "r.html", result, cert, "note <u>")
    write_json(tmp_path / "r.json", result, cert, "note")
    html = (tmp_path / "r.html").read_text()
    for raw in ("<script>", "<b>cell", "<i>pos", "<x>", "<u>"):
        assert raw not in html
    assert "&lt;script&gt;" in html
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["figures_mm"]["F"] == 0.01 and doc["verdict"] == "incomplete"  # no sphere measured
