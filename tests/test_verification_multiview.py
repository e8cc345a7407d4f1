"""The Part 3 multi-view procedure end to end in the binned simulated cell: the long ball bar measured across
four views of the robot-moved sensor and combined in the world frame."""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.routines import run_routine
from cell.config import load_cell_config
from cell.verification.certificate import load_certificate
from cell.verification.job import VerificationJob
from cell.verification.multiview import VIEW_SHIFT_MM, bar_pose, view_targets
from cell.verification.positions import Volume
from cell.verification.procedure import AcceptanceResult


def test_each_sphere_is_inside_both_of_its_views() -> None:
    cfg = load_cell_config("recipes/cells/sim_binned.yaml")
    vol = Volume.of(cfg.sensor)
    T = bar_pose(30.0)
    targets = view_targets(T, 300.0)
    assert len(targets) == 4  # the bar spans four views
    for sign, pair in ((-1, targets[:2]), (1, targets[2:])):
        centre = T[:3, 3] + sign * 150.0 * T[:3, 0]
        for t in pair:
            assert np.linalg.norm(t - centre) == pytest.approx(VIEW_SHIFT_MM)
            assert VIEW_SHIFT_MM + 12.7 < vol.height_mm / 2  # the sphere stays in the field whatever the yaw


def test_ideal_world_spacing_across_views(tmp_path) -> None:
    cfg = load_cell_config("recipes/cells/sim_binned.yaml")  # world: ideal
    cert = load_certificate()
    job = VerificationJob(cfg, cert, part=3, directions={"along x": 0.0})
    result = AcceptanceResult.from_dict(run_routine(job, tmp_path / "v", None))
    (bar,) = result.positions
    assert bar.error is None and len(bar.ps_mm) == 2
    # exact robot, exact hand-eye: the views agree and the spacing error is the noise floor
    assert abs(bar.sd_mm) < 0.01
    assert all(abs(v) < 0.05 for v in bar.ps_mm)
    assert result.required == ("PF", "PS", "SD") and result.figures_mm["F"] is None
    assert result.verdict in ("pass", "fail")  # F is not part of Part 3's verdict
