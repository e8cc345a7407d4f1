"""Report files and `cell compare`: PLY scalar field, json fields against the injected dent, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.analysis.compare import run_compare
from cell.errors import ConfigError


@pytest.fixture()
def plate(tmp_path: Path) -> tuple[Path, np.ndarray]:
    mesh = trimesh.creation.box(extents=(100.0, 60.0, 4.0))
    path = tmp_path / "nominal.stl"
    mesh.export(path)
    rng = np.random.default_rng(2)
    xy = rng.uniform([-45, -25], [45, 25], (5000, 2))
    r = np.hypot(xy[:, 0] - 20, xy[:, 1])
    z = 2.0 - 0.8 * np.clip(1 - r / 5.0, 0, None)  # a 0.8 mm deep cone dent of radius 5 mm at (20, 0)
    return path, np.column_stack([xy, z])


def test_compare_writes_report_with_dent_region(plate, tmp_path: Path) -> None:
    nominal, pts = plate
    cloud = tmp_path / "cloud.csv"
    np.savetxt(cloud, pts, delimiter=",", header="x,y,z", comments="")
    doc = run_compare(nominal, cloud, tmp_path / "out", tolerance="-0.3,0.3", pictures=False, csv=True)
    expected = pts[:, 2] - 2.0
    assert doc["verdict"] == "fail"
    assert doc["n_out_of_tolerance"] == int((expected < -0.3).sum())
    assert doc["deviation"]["min_mm"] == pytest.approx(expected.min(), abs=1e-9)
    top = doc["regions"][0]
    assert (
        top["kind"] == "dent" and np.hypot(top["centre_mm"][0] - 20, top["centre_mm"][1]) < 3.1
    )  # inside the out-of-tolerance disc
    assert top["n_points"] == doc["n_out_of_tolerance"]
    out = tmp_path / "out"
    assert json.loads((out / "report.json").read_text())["verdict"] == "fail"
    ply = trimesh.load(out / "cloud.ply", process=False)  # an independent PLY reader sees the scalar field
    dev = np.asarray(ply.metadata["_ply_raw"]["vertex"]["data"]["deviation"])
    assert np.allclose(dev, expected, atol=1e-6)
    csv = np.loadtxt(out / "deviations.csv", delimiter=",", skiprows=1)
    assert np.allclose(csv[:, 3], expected, atol=1e-5)
    assert (out / "report.html").read_text().index("FAIL") < 1000  # verdict first


def test_html_has_embedded_pictures(plate, tmp_path: Path) -> None:
    nominal, pts = plate
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, pts[::10])
    doc = run_compare(nominal, cloud, tmp_path / "o")
    html = (tmp_path / "o" / "report.html").read_text()
    assert html.count("data:image/png;base64,") == len(doc["views"]) == 4
    assert html.count("<svg") == 1 and html.count("<rect") > 3  # the histogram
    assert not (tmp_path / "o" / "deviations.csv").exists()  # compare writes the CSV on request only


def test_bad_input_is_a_config_error(plate, tmp_path: Path) -> None:
    nominal, pts = plate
    nan = tmp_path / "nan.xyz"
    np.savetxt(nan, np.full((5, 3), np.nan))
    with pytest.raises(ConfigError, match="no finite points"):
        run_compare(nominal, nan, tmp_path / "o1")
    metres = tmp_path / "m.xyz"
    np.savetxt(metres, pts / 1000.0)
    with pytest.raises(ConfigError, match="wrong units"):
        run_compare(nominal, metres, tmp_path / "o2")
    with pytest.raises(ConfigError):
        run_compare(nominal, metres, tmp_path / "o3", tolerance="0.3,-0.3")


def test_nan_points_are_excluded_and_reported(plate, tmp_path: Path) -> None:
    nominal, pts = plate
    pts = pts.copy()
    pts[:7] = np.nan
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, pts)
    doc = run_compare(nominal, cloud, tmp_path / "o", pictures=False)
    assert doc["excluded"]["non_finite_points"] == 7 and doc["n_points"] == len(pts) - 7


def test_isolated_spikes_are_outliers_but_a_defect_is_a_region() -> None:
    """Single-point spikes 3 mm apart on a 0.1 mm grid are isolated outliers; a 2 mm dent is one region."""
    from cell.analysis.report import Tolerance, isolated_out_of_tolerance, out_of_tolerance_regions

    g = np.stack(np.meshgrid(np.arange(0, 60, 0.1), np.arange(0, 60, 0.1)), -1).reshape(-1, 2)
    pts = np.c_[g, np.zeros(len(g))]
    dev = np.zeros(len(pts))
    spikes = np.flatnonzero((np.abs(g[:, 0] % 3) < 1e-6) & (np.abs(g[:, 1] % 3) < 1e-6))[:30]
    dev[spikes] = 1.0
    dent = np.linalg.norm(g - 45.05, axis=1) < 1.0
    dev[dent] = -0.5
    tol = Tolerance(-0.3, 0.3)
    isolated = isolated_out_of_tolerance(pts, dev, tol, min_points=10)
    assert set(np.flatnonzero(isolated)) == set(spikes)
    regions = out_of_tolerance_regions(pts[~isolated], dev[~isolated], tol)
    assert len(regions) == 1 and regions[0]["kind"] == "dent" and regions[0]["n_points"] == int(dent.sum())


def test_open_nominal_is_reported_as_a_warning(tmp_path) -> None:
    import trimesh

    from cell.analysis.errormap import NominalMesh

    closed = NominalMesh.from_trimesh(trimesh.creation.box(extents=(10, 10, 10)))
    assert closed.sign_warning() is None
    box = trimesh.creation.box(extents=(10, 10, 10))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)  # one face missing
    warning = NominalMesh.from_trimesh(open_box).sign_warning()
    assert warning is not None and "3 edge(s)" in warning
