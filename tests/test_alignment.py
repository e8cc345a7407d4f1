"""Alignment of a part that does not sit where its recipe says (cell/analysis/alignment.py), on a sampled
pillar moved by a known placement error: datums (3-2-1) and datum ICP recover it, kinematic alignment does
not, best fit warns; bad datums are refused at load time with the field named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from cell.analysis.alignment import BEST_FIT_WARNING, Aligner, AlignmentError, check_datums
from cell.config import AlignmentConfig, Recipe, load_recipe, validate
from cell.errors import ConfigError
from cell.geometry import invert, make_pose, transform_points
from cell.mesh import load_mesh

REPO = Path(__file__).resolve().parent.parent
PILLAR = REPO / "recipes" / "pillar.yaml"


@pytest.fixture(scope="module")
def pillar() -> tuple[trimesh.Trimesh, AlignmentConfig]:
    recipe = load_recipe(PILLAR)
    return load_mesh(recipe.part.cad), recipe.alignment


@pytest.fixture(scope="module")
def misplaced(pillar: tuple[trimesh.Trimesh, AlignmentConfig]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pillar's outer surface as a noisy cloud, placed 1 mm / 0.5 deg off (yaw about its centre, as the
    simulated world places it): (nominal points, cloud, the placement error)."""
    mesh, _ = pillar
    pts, face = trimesh.sample.sample_surface(mesh, 250_000, seed=3)
    pts = pts[mesh.face_normals[face][:, 2] > 0.0]  # what a sensor above sees: no inner skin of the sheet
    E = make_pose(Rotation.from_rotvec([0, 0, np.deg2rad(0.5)]).as_matrix(), [0.6, -0.8, 0.0])
    cloud = transform_points(E, pts) + np.random.default_rng(0).normal(0, 0.02, pts.shape)
    return pts, cloud, E


def _error_mm(T: np.ndarray, E: np.ndarray, pts: np.ndarray) -> float:
    """Largest distance over the part between where the alignment puts a point and where it belongs."""
    return float(np.linalg.norm(transform_points(T @ E, pts) - pts, axis=1).max())


def test_datums_recover_the_placement_and_kinematic_does_not(pillar, misplaced) -> None:
    mesh, cfg = pillar
    pts, cloud, E = misplaced
    aligner = Aligner(cfg.model_copy(update={"method": "datums"}), mesh)
    datums = aligner.align(cloud)
    assert _error_mm(datums.T, E, pts) < 0.02  # 0.02 mm noise per point, thousands of points per datum
    assert datums.uncertainty_mm is not None and datums.uncertainty_mm["max"] < 0.02
    assert max(abs(r["after_mm"]) for r in datums.residuals) < 1e-3  # six constraints, six unknowns: met
    assert max(abs(r["before_mm"]) for r in datums.residuals) > 0.5  # the misplacement as the datums saw it
    assert datums.correction_mm == pytest.approx(_error_mm(np.eye(4), E, pts), abs=0.05)
    icp = Aligner(cfg.model_copy(update={"method": "datum_icp"}), mesh).align(cloud)
    assert _error_mm(icp.T, E, pts) < 0.02
    kinematic = Aligner(cfg.model_copy(update={"method": "kinematic"}), mesh).align(cloud)
    assert np.array_equal(kinematic.T, np.eye(4)) and kinematic.warnings
    assert _error_mm(kinematic.T, E, pts) > 2.0
    assert max(abs(r["before_mm"]) for r in kinematic.residuals) > 0.5  # the datums show how far off it is


def test_weighted_combination_and_best_fit(pillar, misplaced) -> None:
    mesh, cfg = pillar
    pts, cloud, E = misplaced
    only_datums = {"kinematic": 0.0, "features": 0.0, "datums": 1.0, "datum_icp": 1.0}
    weighted = Aligner(cfg.model_copy(update={"method": "weighted", "weights": only_datums}), mesh).align(
        cloud
    )
    assert _error_mm(weighted.T, E, pts) < 0.02
    assert set(weighted.estimates) == {"datums", "datum_icp"}
    # eq 4.21 with the kinematic chain weighted in: the result lies between, and the report says how far apart
    mixed = {"kinematic": 1.0, "features": 0.0, "datums": 1.0, "datum_icp": 0.0}
    half = Aligner(cfg.model_copy(update={"method": "weighted", "weights": mixed}), mesh).align(cloud)
    assert 0.3 * _error_mm(np.eye(4), E, pts) < _error_mm(half.T, E, pts) < 0.7 * _error_mm(np.eye(4), E, pts)
    assert half.uncertainty_mm["disagreement_max"] > 1.0
    best = Aligner(cfg.model_copy(update={"method": "best_fit"}), mesh).align(cloud)
    assert _error_mm(best.T, E, pts) < 0.05 and BEST_FIT_WARNING in best.warnings


def test_an_unmeasured_datum_or_a_huge_correction_is_an_alignment_error(pillar, misplaced) -> None:
    mesh, cfg = pillar
    pts, cloud, E = misplaced
    a1 = np.asarray(cfg.datums[0].point_mm)
    far = cloud[np.linalg.norm(cloud - a1, axis=1) > 20]  # nothing measured near datum A1
    with pytest.raises(AlignmentError, match="datum 'A1' not measured"):
        Aligner(cfg.model_copy(update={"method": "datums"}), mesh).align(far)
    tight = cfg.model_copy(update={"method": "datums", "max_correction_mm": 0.5})
    with pytest.raises(AlignmentError, match="max_correction_mm"):
        Aligner(tight, mesh).align(cloud)


def test_bad_datums_are_refused_with_the_field_named(pillar, tmp_path: Path) -> None:
    mesh, cfg = pillar
    off = [d.model_copy() for d in cfg.datums]
    off[3] = off[3].model_copy(update={"point_mm": (-119.88, -54.29, 15.31)})  # 10 mm off the wall
    with pytest.raises(
        ConfigError, match=r"alignment\.datums\[3\]\.point_mm.*'B1' is .* mm from the nominal"
    ):
        check_datums(off, mesh, str(PILLAR))
    same_face = [d.model_copy(update={"point_mm": cfg.datums[0].point_mm}) for d in cfg.datums]
    with pytest.raises(ConfigError, match="six degrees of freedom"):
        check_datums(same_face, mesh, str(PILLAR))
    data = yaml.safe_load(PILLAR.read_text())
    data["alignment"]["datums"] = data["alignment"]["datums"][:4]
    with pytest.raises(ConfigError, match="at least 6 datum points"):
        validate(Recipe, data, tmp_path / "r.yaml")
    data["alignment"] = {"method": "datums", "datums": [{"name": "A", "point_mm": [0, 0, 0]}] * 6}
    with pytest.raises(ConfigError, match="repeated: A"):
        validate(Recipe, data, tmp_path / "r.yaml")


def test_world_placement_matches_what_the_alignment_must_undo() -> None:
    """The simulated world's placement error is a yaw about the part's footprint centre and an in-plane
    shift (fakes.sim.world.place_about); the e2e test in test_inspect_alignment.py uses it as truth."""
    from fakes.sim.world import place_about

    E = make_pose(Rotation.from_rotvec([0, 0, 0.01]).as_matrix(), [1.0, 0.0, 0.0])
    T = place_about(E, np.array([10.0, 20.0, 5.0]))
    np.testing.assert_allclose(transform_points(T, [10.0, 20.0, 0.0]), [11.0, 20.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)
