"""The single sphere's procedure (VDI/VDE 2634 Part 2, PF and PS): its positions fill the measuring volume,
its evaluation recovers an analytic sphere among clutter, and the acceptance figures take PF and PS from
it."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import load_cell_config
from cell.errors import ConfigError
from cell.geometry import make_pose
from cell.verification.certificate import load_certificate
from cell.verification.positions import Volume, sphere_positions
from cell.verification.procedure import (
    AcceptanceResult,
    PositionResult,
    acceptance_positions,
    evaluate_sphere,
)


def test_sphere_positions_reach_the_corners_and_stay_inside() -> None:
    cfg = load_cell_config("recipes/cells/sim.yaml")
    cert = load_certificate()
    vol = Volume.of(cfg.sensor)
    r = cert.sphere.diameter_mm / 2
    pos = sphere_positions(vol, cert.sphere.diameter_mm)
    assert len(pos) == 10 and all(p.artefact == "sphere" for p in pos)
    c = np.array([p.T_V_A[:3, 3] for p in pos])
    d = vol.depth_mm / 2
    assert (np.abs(c[:, 2]) + r <= d).all()  # the whole sphere inside the depth
    for x, y, z in c:  # ... and inside the field where its near side is
        hw, hh = vol.half_field_at(z - r)
        assert abs(x) + r <= hw and abs(y) + r <= hh
    corners = c[:8]
    # the corners: all four quadrants at both depths, well out toward the field's edges
    assert {(np.sign(x), np.sign(y), np.sign(z)) for x, y, z in corners} == {
        (sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)
    }
    assert (np.abs(corners[:, 0]) > 0.6 * vol.width_mm / 2).all()
    assert (np.abs(corners[:, 2]) > 0.6 * d).all()
    labels = [p.label for p in acceptance_positions(cfg, cert)]
    assert len(labels) == 23 and labels[:10] == [p.label for p in pos]
    with pytest.raises(ConfigError, match="does not fit"):
        sphere_positions(vol, 120.0)


def test_evaluate_sphere_finds_the_sphere_among_other_points() -> None:
    """An exact sphere off its commanded pose by 3 mm, with a plane behind it and stray points: the gates keep
    the sphere's points only, and PF and PS are those of the sphere (with 4 um noise: PS within 1 um)."""
    cert = load_certificate()
    R = cert.sphere.diameter_mm / 2
    rng = np.random.default_rng(3)
    true_c = np.array([30.0, -20.0, 410.0])
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] < -0.2]  # the cap facing the camera at the origin
    noise = rng.normal(0, 0.004, len(u))
    sphere = true_c + (R + noise)[:, None] * u
    xy = rng.uniform(-60, 60, size=(20000, 2))
    behind = np.column_stack([xy + true_c[:2], np.full(len(xy), true_c[2] + 40.0)])
    stray = true_c + rng.uniform(-30, 30, size=(200, 3))
    pts = np.vstack([sphere, behind, stray])
    commanded = make_pose(np.eye(3), true_c + (3.0, 0.0, 0.0))
    res = evaluate_sphere(pts, commanded, cert.sphere)
    assert res.artefact == "sphere" and len(res.pf_mm) == len(res.ps_mm) == 1
    assert abs(res.ps_mm[0]) < 0.001
    assert res.rms_mm[0] == pytest.approx(0.004, rel=0.1)
    # PF is the range of the noise left after the 0.3 % rule: about 6 sigma for a Gaussian
    assert 4 * 0.004 < res.pf_mm[0] < 8 * 0.004
    assert res.n_points + res.excluded_points <= len(sphere) + 5  # (almost) nothing but the sphere


def test_pf_and_ps_come_from_the_sphere_when_it_was_measured() -> None:
    def result(positions):
        r = AcceptanceResult(
            cell="c",
            geometry_source="g",
            volume_mm={"width": 200.0, "height": 150.0, "depth": 100.0, "L0": 269.0},
            mpe_mm={"PF": 0.05, "PS": 0.05, "SD": 0.025, "F": 0.05},
            positions=positions,
        )
        r.summarise()
        return r

    sphere = PositionResult("sphere, far top left", "sphere", pf_mm=[0.03], ps_mm=[-0.01])
    bar = PositionResult("ball bar", "ball_bar", pf_mm=[0.07, 0.02], ps_mm=[0.06, 0.0], sd_mm=0.01)
    plane = PositionResult("plane", "plane", f_mm=0.02)
    with_sphere = result([sphere, bar, plane])
    assert with_sphere.figures_mm["PF"] == 0.03 and with_sphere.figures_mm["PS"] == -0.01
    assert with_sphere.verdict == "pass"
    without = result([bar, plane])  # the interim check: the ball bar's spheres stand in
    assert without.figures_mm["PF"] == 0.07 and without.figures_mm["PS"] == 0.06
    assert without.verdict == "fail"
