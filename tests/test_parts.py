"""The committed demo parts: regenerated identically, closed outward solids, and their truth files agree with
what is measured on the meshes themselves (proximity queries, ray casts, face geometry)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.config import load_recipe
from cell.mesh import load_mesh

ROOT = Path(__file__).resolve().parent.parent
PARTS = ROOT / "recipes" / "parts"
DISSERTATION_SLOTS_UM = [32.0, 24.0, 14.0, 6.0]  # Shi, Fig. 5.4, left to right
MESHES = ["pillar_nominal.stl", "pillar_actual.stl", "pillar_actual_ok.stl", "gauge.stl"]
TRUTHS = ["pillar_actual.truth.json", "pillar_actual_ok.truth.json", "gauge.truth.json"]


def _generator():
    spec = importlib.util.spec_from_file_location("make_parts", PARTS / "make_parts.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file executes
    spec.loader.exec_module(module)
    return module


def _truth(name: str) -> dict:
    return json.loads((PARTS / name).read_text())


def _close(a, b, atol: float) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], atol) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y, atol) for x, y in zip(a, b, strict=True))
    if isinstance(a, float):
        return abs(a - b) <= atol
    return a == b


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("parts")
    _generator().make_parts(out)
    return out


@pytest.fixture(scope="module")
def nominal() -> trimesh.Trimesh:
    return load_mesh(PARTS / "pillar_nominal.stl")


def test_regeneration_is_deterministic_and_matches_the_committed_files(regenerated, tmp_path):
    again = tmp_path / "again"
    _generator().make_parts(again)
    for name in MESHES + TRUTHS:  # two runs on one machine: identical bytes
        assert (again / name).read_bytes() == (regenerated / name).read_bytes(), name
    for name in MESHES:  # committed files: same topology, coordinates within float32 rounding
        new, old = (trimesh.load(d / name, process=False) for d in (regenerated, PARTS))
        np.testing.assert_array_equal(new.faces, old.faces)
        np.testing.assert_allclose(new.vertices, old.vertices, rtol=0, atol=1e-4)
    for name in TRUTHS:
        assert _close(json.loads((regenerated / name).read_text()), _truth(name), 1e-6), name


@pytest.mark.parametrize("name", MESHES)
def test_parts_are_closed_outward_solids_on_the_table(name):
    mesh = load_mesh(PARTS / name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-6)
    centre_xy = mesh.bounds[:, :2].mean(axis=0)
    np.testing.assert_allclose(centre_xy, 0.0, atol=1e-4)


def test_pillar_size_and_sheet(nominal):
    assert 18_000 <= len(nominal.faces) <= 24_000
    length, width, height = nominal.extents
    assert 450 <= length <= 500 and 120 <= width <= 200 and 30 <= height <= 60
    # sheet thickness: a vertical ray through the flat top face meets the outer and the inner skin
    origin = np.array([[0.0, 0.0, 200.0]])
    # aim at the middle of the top face at mid-length (the spine bows in +y there)
    top_y = nominal.vertices[np.abs(nominal.vertices[:, 0]) < 3][:, 1].mean()
    origin[0, 1] = top_y
    hits, _, _ = nominal.ray.intersects_location(origin, [[0.0, 0.0, -1.0]], multiple_hits=True)
    z = np.sort(hits[:, 2])[::-1]
    assert z[0] - z[1] == pytest.approx(2.0, abs=0.02)  # top face nearly level across; slope < 5 deg


def test_pillar_has_hat_walls_and_smooth_bends(nominal):
    tilt = np.degrees(np.arccos(np.clip(np.abs(nominal.face_normals[:, 2]), 0, 1)))
    area = nominal.area_faces
    walls = area[(tilt > 62) & (tilt < 78)].sum()
    assert walls > 0.1 * area.sum()  # the inclined side walls of the hat
    # rounded bends: the 70 deg hat bends are split into steps under 20 deg; only the sheet's cut edges (90)
    # and the emboss ramp (one ~45 mm wide spot) have steeper steps
    angle = np.degrees(nominal.face_adjacency_angles)
    assert not np.any((angle > 45) & (angle < 85))
    steep = nominal.vertices[nominal.face_adjacency_edges].mean(axis=1)[(angle > 20) & (angle < 85)]
    assert len(steep) > 0 and np.all(np.ptp(steep[:, :2], axis=0) < 45)


def test_dent_depth_and_centre_measured_against_nominal(nominal):
    truth = _truth("pillar_actual.truth.json")
    actual = load_mesh(PARTS / truth["part"])
    closest, _, tri = trimesh.proximity.closest_point(nominal, actual.vertices)
    signed = np.einsum("ij,ij->i", actual.vertices - closest, nominal.face_normals[tri])  # + = outside
    deepest = int(np.argmin(signed))
    assert -signed[deepest] == pytest.approx(truth["depth_mm"], rel=0.01)
    assert np.linalg.norm(closest[deepest] - truth["centre_mm"]) < 0.5
    moved = actual.vertices[deepest] - nominal.vertices[deepest]  # same topology
    assert moved / np.linalg.norm(moved) @ np.array(truth["direction"]) > 0.999
    # nothing else moved beyond the dent radius (float32 rounding of the STL only)
    far = np.linalg.norm(closest - truth["centre_mm"], axis=1) > truth["radius_mm"] + 2.5
    assert np.abs(signed[far]).max() < 1e-4


def test_undented_actual_is_well_within_tolerance(nominal):
    truth = _truth("pillar_actual_ok.truth.json")
    recipe = load_recipe(ROOT / "recipes" / "pillar.yaml")
    ok = load_mesh(PARTS / truth["part"])
    dist = np.abs(trimesh.proximity.closest_point(nominal, ok.vertices)[1])
    assert truth["max_deviation_mm"] * 0.9 < dist.max() <= truth["max_deviation_mm"] + 1e-4
    assert dist.max() < 0.25 * min(-recipe.tolerance.lower, recipe.tolerance.upper)


def test_gauge_slot_depths_from_the_mesh_geometry():
    truth = _truth("gauge.truth.json")
    gauge = load_mesh(PARTS / "gauge.stl")  # float32 STL: ulp at z = 30 mm is 1.9e-6 mm
    up = gauge.face_normals[:, 2] > 0.999
    centroids = gauge.triangles_center[up]
    top = centroids[:, 2].max()
    assert top == pytest.approx(truth["top_z_mm"], abs=1e-5)
    floors = np.unique(np.round(centroids[:, 2], 6))
    floors = floors[(floors > top - 0.1) & (floors < top)]
    depth_um_by_x = []
    for z in floors:
        faces = gauge.triangles[up][np.abs(centroids[:, 2] - z) < 5e-7]
        x = faces[..., 0]
        depth_um_by_x.append((x.min(), x.max(), (top - z) * 1e3))
    depth_um_by_x.sort()
    measured = [d for _, _, d in depth_um_by_x]
    np.testing.assert_allclose(measured, DISSERTATION_SLOTS_UM, atol=0.1)  # 0.1 um
    np.testing.assert_allclose(measured, [s["depth_um"] for s in truth["slots"]], atol=0.1)
    for (x0, x1, _), slot in zip(depth_um_by_x, truth["slots"], strict=True):
        np.testing.assert_allclose([x0, x1], slot["x_range_mm"], atol=1e-5)


@pytest.mark.parametrize("name", ["pillar", "pillar_glossy", "gauge"])
def test_recipes_load_and_point_at_valid_parts(name):
    recipe = load_recipe(ROOT / "recipes" / f"{name}.yaml")
    for path in (recipe.part.cad, recipe.part.actual):
        assert path.is_file()
        load_mesh(path)


def test_glossy_recipe_is_glossier_than_the_plain_one():
    plain = load_recipe(ROOT / "recipes" / "pillar.yaml").part.material
    glossy = load_recipe(ROOT / "recipes" / "pillar_glossy.yaml").part.material
    assert glossy.specular > 10 * plain.specular and glossy.shininess > 5 * plain.shininess
    assert glossy.specular > glossy.albedo  # the highlight outshines the diffuse return


def test_the_gauge_is_as_its_certificate_says():
    """The simulated gauge is exactly as certified (as the verification artefacts): the certificate's slots
    are the mesh's; a certificate with a wrong field is refused, naming the file and the field."""
    from cell.calibration.validation import load_gauge_certificate

    cert = load_gauge_certificate(PARTS / "gauge.certificate.yaml")
    truth = _truth("gauge.truth.json")
    assert cert.mesh == (PARTS / truth["part"]).resolve() and cert.top_z_mm == truth["top_z_mm"]
    for s, t in zip(cert.slots, truth["slots"], strict=True):
        assert s.depth_um == t["depth_um"]
        assert list(s.x_range_mm) == t["x_range_mm"] and list(s.y_range_mm) == t["y_range_mm"]


def test_a_bad_gauge_certificate_names_its_field(tmp_path):
    from cell.calibration.validation import load_gauge_certificate
    from cell.errors import ConfigError

    bad = tmp_path / "gauge.yaml"
    text = (PARTS / "gauge.certificate.yaml").read_text()
    bad.write_text(text.replace("depth_um: 24.0", "depth_um: -24.0"))
    with pytest.raises(ConfigError) as err:
        load_gauge_certificate(bad)
    assert "gauge.yaml" in str(err.value) and "slots.1.depth_um" in str(err.value)
