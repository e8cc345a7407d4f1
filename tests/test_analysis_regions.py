"""Per-region verdicts and coverage: a plate measured densely on half of its top, sparsely on the other."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cell.analysis.compare import run_compare
from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.regions import Region, Tolerance, coverage
from cell.analysis.report import ReportInput, summarise
from cell.errors import ConfigError

PLATE = (100.0, 60.0, 4.0)  # box centred at the origin: top face z = 2, area 2 (6000 + 400 + 240) mm^2
AREA = 2 * (100 * 60 + 100 * 4 + 60 * 4)


def _grid(x0: float, x1: float, step: float) -> np.ndarray:
    x, y = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(-30 + step / 2, 30, step))
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)])


def _plate_cloud() -> tuple[trimesh.Trimesh, NominalMesh, np.ndarray]:
    mesh = trimesh.creation.box(extents=PLATE)
    # Left half of the top at 4 points/mm^2 (0.5 mm grid), right half at 0.25 points/mm^2 (2 mm grid).
    pts = np.vstack([_grid(-50, 0, 0.5), _grid(0, 50, 2.0)])
    return mesh, NominalMesh.from_trimesh(mesh), pts


def test_coverage_counts_area_measured_at_the_required_density() -> None:
    _, nm, pts = _plate_cloud()
    em = signed_distance(nm, pts)
    # Required 1 point/mm^2 within 1.5 mm (>= 8 points): only the dense half (3000 mm^2) qualifies.
    c = coverage(nm, em.closest_mm, density_per_mm2=1.0, radius_mm=1.5)
    assert c.min_count == 8 and c.area_mm2 == pytest.approx(AREA)
    # Plus the side faces just under the dense patch's 160 mm of plate edge: a side sample at depth d sees a
    # half disc of radius sqrt(1.5^2 - d^2) of the 4/mm^2 grid, >= 8 points while d < 0.99 mm.
    assert c.fraction == pytest.approx((3000 + 160 * 0.99) / AREA, abs=0.006)
    # A radius alone (one point within 1.5 mm): the 2 mm grid covers too (farthest spot sqrt(2) mm away).
    c1 = coverage(nm, em.closest_mm, radius_mm=1.5)
    # Side strips: under the dense half the nearest row is 0.25 mm in (depth < 1.48 mm), under the sparse half
    # 1 mm in and up to 1 mm along the edge (mean depth of int_0^1 sqrt(1.25 - t^2) dt = 0.93 mm).
    assert c1.fraction == pytest.approx((6000 + 160 * 1.48 + 160 * 0.93) / AREA, abs=0.006)


def test_region_verdicts_boxes_faces_and_own_tolerances() -> None:
    mesh, nm, pts = _plate_cloud()
    pts = pts.copy()
    dent = np.hypot(pts[:, 0] + 25, pts[:, 1]) < 3  # a 0.5 mm dent in the dense half at (-25, 0)
    pts[dent, 2] -= 0.5
    em = signed_distance(nm, pts)
    cov = coverage(nm, em.closest_mm, density_per_mm2=1.0, radius_mm=1.5)
    bottom = np.flatnonzero(mesh.face_normals[:, 2] < -0.9)
    regions = [
        Region("dense-top", box_mm=((-50, -30, 1), (0, 30, 3))),
        Region("sparse-top", box_mm=((0, -30, 1), (50, 30, 3))),
        Region("bottom", faces=bottom),
    ]
    tol = Tolerance(-0.3, 0.3)

    def doc(regs: list[Region], min_cov: float | None = None) -> dict:
        face = nm.source_face[em.face]
        return summarise(ReportInput(pts, em.deviation_mm, tol, len(pts), {}, {}, face, regs, cov, min_cov))

    d = doc(regions, min_cov=0.9)
    v = {r["name"]: r for r in d["region_verdicts"]}
    assert v["dense-top"]["verdict"] == "fail" and v["dense-top"]["n_out_of_tolerance"] == dent.sum()
    assert v["dense-top"]["min_mm"] == pytest.approx(-0.5, abs=1e-9)
    assert v["dense-top"]["coverage"] > 0.97
    assert v["sparse-top"]["verdict"] == "incomplete" and v["sparse-top"]["coverage"] < 0.03
    assert v["bottom"]["verdict"] == "no_data" and v["bottom"]["n_points"] == 0
    assert d["verdict"] == "fail" and d["regions"][0]["verdict"] == "fail"  # the dent cluster
    # A looser band of its own around the dent passes it, and with it the part (coverage not required).
    # The dent's points are judged by that band everywhere in the report: not out of tolerance, no cluster.
    loose = [Region("dent-zone", box_mm=((-30, -5, 1), (-20, 5, 3)), tolerance=Tolerance(-1.0, 1.0))]
    d_loose = doc(loose)
    assert d_loose["verdict"] == "pass" and d_loose["region_verdicts"][0]["verdict"] == "pass"
    assert d_loose["n_out_of_tolerance"] == 0 and d_loose["regions"] == []
    # Overlapping bands of their own: both must hold, so a tight pad inside the loose zone fails the dent.
    pad = Region("pad", box_mm=((-27, -2, 1), (-23, 2, 3)), tolerance=Tolerance(-0.05, 0.05))
    in_pad = ((pts >= (-27, -2, 1)) & (pts <= (-23, 2, 3))).all(1)
    d_both = doc([*loose, pad])
    v = {r["name"]: r for r in d_both["region_verdicts"]}
    assert v["dent-zone"]["verdict"] == "pass" and v["pad"]["verdict"] == "fail"
    assert d_both["verdict"] == "fail" and d_both["n_out_of_tolerance"] == (in_pad & dent).sum() > 0
    assert d_both["regions"][0]["n_points"] == (in_pad & dent).sum()
    # A tighter band elsewhere fails the part although every point is inside the report's band.
    pts_ok = pts.copy()
    pts_ok[dent, 2] += 0.4  # dent now 0.1 mm deep
    em = signed_distance(nm, pts_ok)
    face = nm.source_face[em.face]
    tight = [Region("datum-pad", box_mm=((-30, -5, 1), (-20, 5, 3)), tolerance=Tolerance(-0.05, 0.05))]
    d2 = summarise(ReportInput(pts_ok, em.deviation_mm, tol, len(pts), {}, {}, face, tight, cov, None))
    assert d2["verdict"] == "fail" and d2["region_verdicts"][0]["verdict"] == "fail"
    # the 0.1 mm dent is out of the pad's band, so it is out of tolerance and a located region of the report
    assert d2["n_out_of_tolerance"] == dent.sum()
    assert d2["regions"][0]["n_points"] == dent.sum() and d2["regions"][0]["kind"] == "dent"
    assert np.allclose(d2["regions"][0]["centre_mm"][:2], (-25, 0), atol=0.5)
    assert d2["regions"][0]["extreme_mm"] == pytest.approx(-0.1, abs=1e-6)
    # Coverage required over the whole part: 23 % measured -> incomplete.
    d3 = summarise(ReportInput(pts_ok, em.deviation_mm, tol, len(pts), {}, {}, face, [], cov, 0.5))
    assert d3["verdict"] == "incomplete" and d3["coverage_detail"]["min_count"] == 8


def test_compare_with_region_file(tmp_path: Path) -> None:
    mesh, _, pts = _plate_cloud()
    nominal = tmp_path / "plate.stl"
    mesh.export(nominal)
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, pts)
    top = [int(i) for i in np.flatnonzero(mesh.face_normals[:, 2] > 0.9)]
    spec = {
        "regions": [{"name": "top", "faces": top}, {"name": "left", "box_mm": [[-50, -30, 1], [0, 30, 3]]}]
    }
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(spec))
    doc = run_compare(
        nominal,
        cloud,
        tmp_path / "o",
        pictures=False,
        regions=tmp_path / "r.yaml",
        density_per_mm2=1.0,
        radius_mm=1.5,
        min_coverage=0.9,
    )
    v = {r["name"]: r for r in doc["region_verdicts"]}
    assert v["top"]["n_points"] == len(pts) and v["top"]["coverage"] == pytest.approx(0.5, abs=0.02)
    assert v["left"]["verdict"] == "pass" and doc["verdict"] == "incomplete"
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"regions": [{"name": "x"}]}))
    with pytest.raises(ConfigError, match="exactly one"):
        run_compare(nominal, cloud, tmp_path / "o2", pictures=False, regions=tmp_path / "bad.yaml")


def test_compare_excludes_isolated_spikes_on_request(tmp_path: Path) -> None:
    """On the plate's dense half: five single-point spikes 10 mm apart are isolated outliers with
    --min-defect-points 10, the 3 mm dent stays a located region; by default every point counts."""
    mesh, _, pts = _plate_cloud()
    pts = pts.copy()
    dense = np.flatnonzero(pts[:, 0] < -5)
    spikes = dense[
        np.isin(np.round(pts[dense, 0], 3), (-45.25, -35.25)) & np.isin(pts[dense, 1], (-20.25, 0.25, 20.25))
    ]
    pts[spikes[:5], 2] += 1.0
    dent = np.hypot(pts[:, 0] + 15, pts[:, 1]) < 3
    pts[dent, 2] -= 0.5
    nominal = tmp_path / "plate.stl"
    mesh.export(nominal)
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, pts)
    every = run_compare(nominal, cloud, tmp_path / "a", pictures=False)
    assert every["n_out_of_tolerance"] == dent.sum() + 5 and len(every["regions"]) == 6
    filtered = run_compare(nominal, cloud, tmp_path / "b", pictures=False, min_defect_points=10)
    assert filtered["excluded"]["isolated_out_of_tolerance_points"] == 5
    assert filtered["n_points"] == len(pts) - 5 and filtered["n_out_of_tolerance"] == dent.sum()
    (region,) = filtered["regions"]
    assert region["kind"] == "dent" and np.allclose(region["centre_mm"][:2], (-15, 0), atol=0.3)
    with pytest.raises(ConfigError, match="min-defect-points"):
        run_compare(nominal, cloud, tmp_path / "c", pictures=False, min_defect_points=0)
