"""The one judging pipeline (cell.analysis.judge) against a plate measured with known offsets: the deviations,
bands, isolated outliers, exclusions and verdicts follow from the construction, not from the error map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.analysis.errormap import ErrorMap, NominalMesh
from cell.analysis.judge import judge
from cell.analysis.regions import Coverage, Region, Tolerance, coverage
from cell.analysis.report import summarise, write_report

PLATE = (100.0, 60.0, 4.0)  # box centred at the origin: top face z = 2, side x = +50


def _plate() -> tuple[trimesh.Trimesh, NominalMesh]:
    mesh = trimesh.creation.box(extents=PLATE)
    return mesh, NominalMesh.from_trimesh(mesh)


def _top(offset_mm: float, step: float = 1.0) -> np.ndarray:
    """The top face sampled on a grid, lifted ``offset_mm`` along its outward normal (+z)."""
    x, y = np.meshgrid(np.arange(-49.5, 50, step), np.arange(-29.5, 30, step))
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 2.0 + offset_mm)])


def test_known_offsets_give_their_deviations_faces_and_verdicts(tmp_path: Path) -> None:
    mesh, nominal = _plate()
    top = _top(0.1)
    side_y, side_z = np.meshgrid(np.arange(-29.5, 30, 1.0), np.arange(-1.5, 2, 1.0))
    side = np.column_stack([np.full(side_y.size, 50.0 - 0.2), side_y.ravel(), side_z.ravel()])  # 0.2 mm in
    pts = np.vstack([top, side])
    inp = judge(nominal, pts, Tolerance(-0.3, 0.3), excluded={"table_points": 7})
    truth = np.concatenate([np.full(len(top), 0.1), np.full(len(side), -0.2)])
    assert np.allclose(inp.deviation_mm, truth, atol=1e-9)
    normals = mesh.face_normals[inp.source_face]  # faces of the mesh as given
    assert np.allclose(normals[: len(top)], (0, 0, 1)) and np.allclose(normals[len(top) :], (1, 0, 0))
    assert inp.n_points_input == len(pts) and inp.excluded == {"degenerate_triangles": 0, "table_points": 7}
    assert inp.warnings == []  # a closed box: no sign warning
    doc = write_report(tmp_path, inp, pictures=False)
    assert doc["verdict"] == "pass" and doc["n_out_of_tolerance"] == 0
    assert doc["deviation"]["max_mm"] == pytest.approx(0.1) and doc["deviation"]["min_mm"] == pytest.approx(
        -0.2
    )
    # a band that the side's -0.2 mm leaves: exactly the side's points fail
    tight = summarise(judge(nominal, pts, Tolerance(-0.15, 0.15)))
    assert tight["verdict"] == "fail" and tight["n_out_of_tolerance"] == len(side)
    # a region of the top faces with a band of its own that the top's +0.1 mm leaves
    top_faces = np.flatnonzero(mesh.face_normals[:, 2] > 0.9)
    pad = Region("top", faces=top_faces, tolerance=Tolerance(-0.05, 0.05))
    doc = summarise(judge(nominal, pts, Tolerance(-0.3, 0.3), regions=[pad]))
    assert doc["verdict"] == "fail" and doc["n_out_of_tolerance"] == len(top)
    assert (
        doc["region_verdicts"][0]["n_points"] == len(top) and doc["region_verdicts"][0]["verdict"] == "fail"
    )


def test_isolated_spikes_are_set_aside_and_counted() -> None:
    _, nominal = _plate()
    pts = _top(0.0, step=0.5)
    spikes = np.flatnonzero(np.isin(pts[:, 0], (-30.0, 0.0, 30.0)) & (pts[:, 1] == 0.5))
    pts[spikes, 2] += 1.0  # three single points 1 mm high, 30 mm apart
    dent = np.hypot(pts[:, 0] - 15, pts[:, 1] - 10) < 3  # a 3 mm dent: an area, not an outlier
    pts[dent, 2] -= 0.5
    kept = judge(nominal, pts, Tolerance(), min_defect_points=1)
    assert "isolated_out_of_tolerance_points" not in kept.excluded and len(kept.points_mm) == len(pts)
    cut = judge(nominal, pts, Tolerance(), min_defect_points=10, n_points_input=len(pts) + 4)
    assert cut.excluded["isolated_out_of_tolerance_points"] == len(spikes) == 3
    assert len(cut.points_mm) == len(pts) - 3 and cut.n_points_input == len(pts) + 4
    assert np.allclose(cut.deviation_mm, np.where(dent, -0.5, 0.0)[~np.isin(np.arange(len(pts)), spikes)])
    doc = summarise(cut)
    assert doc["verdict"] == "fail" and doc["n_out_of_tolerance"] == dent.sum()
    assert len(doc["regions"]) == 1 and doc["regions"][0]["kind"] == "dent"


def test_coverage_from_the_error_map_of_every_point() -> None:
    _, nominal = _plate()
    pts = _top(0.4)  # every point 0.4 mm out, as one connected sheet: none is isolated
    seen: list[ErrorMap] = []

    def cov(em: ErrorMap) -> Coverage:
        seen.append(em)
        return coverage(nominal, em.closest_mm, radius_mm=1.5)

    inp = judge(nominal, pts, Tolerance(), coverage=cov, min_coverage=0.9, min_defect_points=10)
    (em,) = seen
    assert np.allclose(em.closest_mm[:, 2], 2.0) and len(em.closest_mm) == len(pts)
    # the top, plus strips of the sides less than 1.5 mm below its edge (320 mm long), sampling error aside
    area = 2 * (100 * 60 + 100 * 4 + 60 * 4)
    assert inp.coverage is not None
    assert 6000 / area - 0.01 < inp.coverage.fraction < (6000 + 320 * 1.5) / area + 0.01
    doc = summarise(inp)
    assert doc["verdict"] == "fail" and doc["n_out_of_tolerance"] == len(pts)
