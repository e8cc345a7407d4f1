"""Projector response calibration: the measured exponent matches the simulated projector's gamma, and the
linearising LUT removes the waviness that gamma puts into phase-shifted planes."""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.gamma import apply_lut, fitted_gamma, grey_levels, linearising_lut, measure_response
from cell.calibration.validation import fit_plane
from cell.config import SimConfig
from cell.errors import CalibrationError
from cell.sensing.decode import decode
from cell.sensing.patterns import gcps_patterns
from cell.sensing.triangulate import PinholeTriangulator
from fakes.sim.board import SteppedReferenceBoard
from fakes.sim.testing import small_sensor


@pytest.fixture(scope="module")
def rig():
    return SteppedReferenceBoard(small_sensor(projector={"gamma": 2.2}), SimConfig(seed=3))


def _plane_sigma(rig, patterns, rng):
    cloud = PinholeTriangulator.from_sensor(rig.sensor).triangulate(
        decode(rig.capture(10.0, patterns.frames, rng), patterns, 12)
    )
    return fit_plane(cloud.points_C[cloud.valid])["std_mm"]


def test_gamma_measured_and_linearised(rig):
    rng = np.random.default_rng(4)
    levels = grey_levels(17)
    shape = (rig.sensor.projector.height_px, rig.sensor.projector.width_px)
    frames = np.stack([np.full(shape, g, np.uint8) for g in levels])
    response = measure_response(rig.capture(0.0, frames, rng), levels)
    assert fitted_gamma(levels, response) == pytest.approx(2.2, abs=0.05)
    lut = linearising_lut(levels, response)
    lin = measure_response(rig.capture(0.0, lut[frames], rng), levels)
    assert fitted_gamma(levels, lin) == pytest.approx(1.0, abs=0.05)

    # The waviness is systematic: judge it without sensor noise (which at this small size is larger), against
    # the same sensor with a linear projector.
    quiet = SteppedReferenceBoard(rig.sensor, SimConfig(seed=3, noise=False))
    linear = SteppedReferenceBoard(small_sensor(projector={"gamma": 1.0}), quiet.sim)
    ps = gcps_patterns(128, 96, 8, n_phase=4, direction="columns")
    wavy = _plane_sigma(quiet, ps, rng)
    fixed = _plane_sigma(quiet, apply_lut(ps, lut), rng)
    baseline = _plane_sigma(linear, ps, rng)
    assert fixed < 0.6 * wavy, (wavy, fixed)  # measured 0.075 -> 0.040 mm; 8-bit LUT steps limit the rest
    assert fixed < 2.0 * baseline, (fixed, baseline)  # linear projector: 0.025 mm


def test_bad_response_input():
    with pytest.raises(CalibrationError, match="increase"):
        measure_response(np.zeros((3, 8, 8)), np.array([0, 200, 100]))
    with pytest.raises(CalibrationError, match="too few pixels"):
        measure_response(np.zeros((3, 20, 20)), np.array([0, 128, 255]))


def test_the_inspection_projects_through_the_active_gamma_lut(tmp_path) -> None:
    """A cell whose `calibration.gamma` names a LUT gets every inspection pattern sent through it (what the
    projector then shows is linear in the coded intensity); a file that is not a 256-level LUT is refused
    with its name."""
    import trimesh

    from cell.calibration.store import save_calibration
    from cell.config import DEFAULT_CELL, CalibrationFiles, load_cell_config, load_recipe
    from cell.errors import ConfigError
    from cell.inspection import LambertianInspection

    recipe = load_recipe(DEFAULT_CELL.parent.parent / "pillar.yaml")
    cfg = load_cell_config(DEFAULT_CELL)
    part = trimesh.creation.box((50, 50, 10))
    plain = LambertianInspection(recipe, cfg, part).patterns.frames
    # a linearising LUT keeps 0 and 255, which leaves GCLS's binary frames as they are; this one also lifts
    # the black and caps the white, so the test sees whether the frames went through it
    lut = np.clip(np.round(255 * (np.arange(256) / 255) ** (1 / 2.2)), 10, 245).astype(np.uint8)
    good = save_calibration(tmp_path / "gamma", "projector_gamma", {"lut": lut}, {"projector": {}})
    with_lut = cfg.model_copy(update={"calibration": CalibrationFiles(gamma=good)})
    frames = LambertianInspection(recipe, with_lut, part).patterns.frames
    np.testing.assert_array_equal(frames, lut[plain])
    assert not np.array_equal(frames, plain)
    bad = save_calibration(tmp_path / "bad", "projector_gamma", {"lut": lut[:128]}, {"projector": {}})
    with pytest.raises(ConfigError, match="256 grey levels"):
        bad_cfg = cfg.model_copy(update={"calibration": CalibrationFiles(gamma=bad)})
        LambertianInspection(recipe, bad_cfg, part)


def test_every_measurement_projects_through_the_active_gamma_lut(tmp_path) -> None:
    """Verification, validation, the hand-eye's gauge scans and `cell scan` project the same measuring code as
    the inspection, through the cell's gamma LUT: the line-shift edges are ramped in grey, which a projector's
    uncorrected gamma would bend (they once projected the bare code and only the inspection corrected it)."""
    from cell.calibration.active import active_measuring_patterns
    from cell.calibration.handeye_routines import HandEyeIcpJob
    from cell.calibration.store import save_calibration
    from cell.calibration.validation_routine import ValidateJob
    from cell.config import DEFAULT_CELL, CalibrationFiles, load_cell_config
    from cell.sensing.patterns import measuring_patterns
    from cell.verification.certificate import load_certificate
    from cell.verification.job import VerificationJob

    cfg = load_cell_config(DEFAULT_CELL)
    plain = measuring_patterns(cfg.sensor.projector).frames
    assert ((plain > 0) & (plain < 255)).any()  # the ramps' grey levels: what the LUT must reach
    lut = np.clip(np.round(255 * (np.arange(256) / 255) ** (1 / 2.2)), 10, 245).astype(np.uint8)
    path = save_calibration(tmp_path / "gamma", "projector_gamma", {"lut": lut}, {"projector": {}})
    with_lut = cfg.model_copy(update={"calibration": CalibrationFiles(gamma=path)})
    np.testing.assert_array_equal(active_measuring_patterns(with_lut).frames, lut[plain])
    np.testing.assert_array_equal(active_measuring_patterns(cfg).frames, plain)
    jobs = [
        VerificationJob(with_lut, load_certificate()),
        ValidateJob(with_lut),
        HandEyeIcpJob(with_lut),
    ]
    for job in jobs:
        np.testing.assert_array_equal(
            job.patterns(job.plan()[0]).frames, lut[plain], err_msg=type(job).__name__
        )
