"""Artefact certificate (schema; errors name file and field), artefact meshes, the guideline's positions."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

from cell.config import load_cell_config
from cell.errors import ConfigError
from cell.geometry import transform_points
from cell.verification.artefacts import ball_bar, plane, sphere_artefact
from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate
from cell.verification.figures import fit_sphere
from cell.verification.positions import Volume, ball_bar_positions, plane_positions
from cell.verification.procedure import acceptance_positions
from cell.verification.stage import OperatorStage


def test_shipped_certificate_loads() -> None:
    cert = load_certificate(DEFAULT_CERTIFICATE)
    assert cert.ball_bar.centre_distance_mm == 170.0
    assert cert.ball_bar_long is not None and cert.ball_bar_long.centre_distance_mm >= 290


def test_certificate_errors_name_file_and_field(tmp_path) -> None:
    data = yaml.safe_load(DEFAULT_CERTIFICATE.read_text())
    data["ball_bar"]["centre_distance_mm"] = 15.0  # spheres would overlap
    bad = tmp_path / "cert.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="cert.yaml") as exc:
        load_certificate(bad)
    assert "ball_bar" in str(exc.value)
    data = yaml.safe_load(DEFAULT_CERTIFICATE.read_text())
    data["plane"]["flatnes_mm"] = 0.001  # a typo must not fall back to a default
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="plane.flatnes_mm"):
        load_certificate(bad)


def test_meshes_have_the_certified_dimensions() -> None:
    """A sphere's surface (not its vertices: flat facets lie inside the sphere through them) fits the
    certified diameter, and deviates from it by under a micrometre either way."""
    cert = load_certificate()
    s = sphere_artefact(cert.sphere)
    R = cert.sphere.diameter_mm / 2
    surface = trimesh.sample.sample_surface(s, 100_000, seed=1)[0]
    fit = fit_sphere(surface, outlier_fraction=0)
    assert fit.diameter == pytest.approx(cert.sphere.diameter_mm, abs=1e-5)
    assert np.allclose(fit.centre, 0.0, atol=1e-5)
    out = np.linalg.norm(s.vertices, axis=1) - R  # vertices stand out, facets' middles lie inside
    depth = R - np.abs(np.einsum("ij,ij->i", s.face_normals, s.triangles[:, 0]))
    assert 0 < out.min() and out.max() < 1e-3 and 0 < depth.max() < 1e-3, (out.max(), depth.max())
    bar = ball_bar(cert.ball_bar)
    L = cert.ball_bar.centre_distance_mm
    for sign in (-1, 1):  # the sphere vertices around each end fit the certified centre
        v = bar.vertices[np.abs(np.linalg.norm(bar.vertices - (sign * L / 2, 0, 0), axis=1) - 10.0) < 1e-3]
        f = fit_sphere(v, outlier_fraction=0)
        assert np.allclose(f.centre, (sign * L / 2, 0, 0), atol=1e-9)
    p = plane(cert.plane)
    assert p.bounds[1][2] == pytest.approx(0.0)
    top = p.vertices[np.isclose(p.vertices[:, 2], 0.0)]
    assert np.ptp(top[:, 0]) == pytest.approx(cert.plane.length_mm)
    assert np.ptp(top[:, 1]) == pytest.approx(cert.plane.width_mm)


def test_positions_fill_the_measuring_volume() -> None:
    cfg = load_cell_config("recipes/cells/sim.yaml")
    cert = load_certificate()
    vol = Volume.of(cfg.sensor)
    assert vol.width_mm == pytest.approx(200, abs=1) and vol.height_mm == pytest.approx(150, abs=1)
    bars = ball_bar_positions(vol, 170.0, 20.0)
    assert len(bars) == 7
    ends = np.array([transform_points(p.T_V_A, np.array([[-85.0, 0, 0], [85.0, 0, 0]])) for p in bars])
    # the space diagonals reach into both halves of the depth, every bar stays inside the volume
    assert ends[:4, :, 2].min() < -0.25 * vol.depth_mm and ends[:4, :, 2].max() > 0.25 * vol.depth_mm
    assert (np.abs(ends[..., 0]) < vol.width_mm / 2).all() and (np.abs(ends[..., 2]) < vol.depth_mm / 2).all()
    planes = plane_positions(vol, cert.plane.length_mm)
    normals = np.array([p.T_V_A[:3, 2] for p in planes])
    assert (normals[:, 2] < -0.9).all()  # every face looks at the camera
    assert len(acceptance_positions(cfg, cert)) == 23  # 10 sphere, 7 ball bar, 6 plane positions
    with pytest.raises(ConfigError, match="does not fit"):
        ball_bar_positions(vol, 250.0, 20.0)


def test_operator_stage_says_where_and_waits() -> None:
    said, asked = [], []
    stage = OperatorStage(ask=lambda q: asked.append(q) or "", say=said.append)
    T = np.eye(4)
    T[:3, 3] = (10.0, -20.0, 80.0)
    stage.place("ball_bar", T, "space diagonal 1")
    assert "space diagonal 1" in said[0] and "(10, -20, 80)" in said[0] and len(asked) == 1
