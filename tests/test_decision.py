"""The decision rules (cell/analysis/decision.py) on constructed points: the classes follow from the zones of
ISO 14253-1 (band shrunk and widened by U = k u), the regions and the verdict from the classes, the recipe's
``ambiguous`` setting from what ambiguous points make of the part; cloud.ply carries u and a rebuilt report
judges the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cell.analysis.decision import AMBIGUOUS, CONFORM, NONCONFORM, DecisionRule, classify
from cell.analysis.errormap import NominalMesh
from cell.analysis.judge import judge
from cell.analysis.regions import Region, Tolerance
from cell.analysis.report import summarise, write_report
from cell.analysis.report_files import decode_uncertainty, encode_uncertainty, read_ply_field, read_ply_points
from cell.config import load_recipe
from cell.errors import ConfigError

TOL = Tolerance(-0.1, 0.1)


def test_classes_follow_the_zones() -> None:
    """Band +-0.1, U 0.02: conform within +-0.08 (limits included), not beyond +-0.12, ambiguous between."""
    d = np.array([0.0, 0.05, 0.08, 0.0801, 0.1, 0.119, 0.12, 0.1201, -0.09, -0.13])
    classes = classify(d, TOL, np.full(len(d), 0.02))
    expected = [CONFORM] * 3 + [AMBIGUOUS] * 4 + [NONCONFORM, AMBIGUOUS, NONCONFORM]
    assert classes.tolist() == expected
    # the simple rule is the band itself
    assert classify(d, TOL, np.zeros(len(d))).tolist() == [NONCONFORM if abs(x) > 0.1 else CONFORM for x in d]
    # U wider than half the band: nothing can be shown to conform
    assert CONFORM not in classify(np.zeros(5), TOL, np.full(5, 0.11)).tolist()


def test_guard_is_k_times_u_and_needs_u() -> None:
    rule = DecisionRule("guarded", k=3.0)
    assert rule.guard_mm(3, np.array([0.01, 0.02, np.nan])) == pytest.approx([0.03, 0.06, np.inf])
    with pytest.raises(ValueError, match="uncertainty"):
        rule.guard_mm(3, None)
    assert DecisionRule().guard_mm(3, None).tolist() == [0.0, 0.0, 0.0]


PLATE = (100.0, 60.0, 4.0)  # top face z = 2


def _plate_points(bump_mm: float, bump_points: int = 60) -> tuple[NominalMesh, np.ndarray]:
    """The plate's top face on a 1 mm grid at deviation 0, with a patch of ``bump_points`` (a block of
    neighbours) lifted by ``bump_mm``."""
    nominal = NominalMesh.from_trimesh(trimesh.creation.box(extents=PLATE))
    x, y = np.meshgrid(np.arange(-49.5, 50, 1.0), np.arange(-29.5, 30, 1.0))
    pts = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)])
    patch = np.argsort(np.hypot(pts[:, 0] - 10, pts[:, 1] - 5))[:bump_points]
    pts[patch, 2] += bump_mm
    return nominal, pts


@pytest.mark.parametrize(
    ("bump", "ambiguous", "simple", "guarded"),
    [
        (0.05, "incomplete", "pass", "pass"),  # well inside: both pass
        (0.095, "incomplete", "pass", "incomplete"),  # within U of the limit, inside it
        (0.105, "incomplete", "fail", "incomplete"),  # within U of the limit, beyond it
        (0.105, "fail", "fail", "fail"),
        (0.105, "pass", "fail", "pass"),
        (0.13, "pass", "fail", "fail"),  # beyond the band widened by U: fails under every setting
    ],
)
def test_verdict_follows_the_classes(bump: float, ambiguous: str, simple: str, guarded: str) -> None:
    nominal, pts = _plate_points(bump)
    u = np.full(len(pts), 0.01)  # U = 0.02
    for rule, expected in (("simple", simple), ("guarded", guarded)):
        inp = judge(
            nominal,
            pts,
            TOL,
            min_defect_points=10,
            uncertainty_mm=u,
            decision=DecisionRule(rule, 2.0, ambiguous),  # type: ignore[arg-type]
        )
        doc = summarise(inp)
        assert doc["verdict"] == expected, (rule, doc["decision"])
        assert sum(doc["decision"]["counts"].values()) == len(pts)
    if guarded in ("incomplete",):
        assert any("ambiguous" in r for r in doc["incomplete_reasons"])
        region = doc["decision"]["ambiguous_regions"][0]
        assert region["n_points"] == 60 and region["U_mm"] == pytest.approx(0.02)
        assert np.allclose(region["centre_mm"][:2], (10, 5), atol=1.0)


def test_small_undecided_clusters_are_isolated_outliers() -> None:
    """Three ambiguous neighbours (a mixed-pixel spike) are set aside like isolated out-of-tolerance points;
    the guarded verdict passes."""
    nominal, pts = _plate_points(0.095, bump_points=3)
    inp = judge(
        nominal,
        pts,
        TOL,
        min_defect_points=10,
        uncertainty_mm=np.full(len(pts), 0.01),
        decision=DecisionRule("guarded"),
    )
    doc = summarise(inp)
    assert doc["verdict"] == "pass" and doc["excluded"]["isolated_out_of_tolerance_points"] == 3


def test_region_verdicts_use_the_guard() -> None:
    nominal, pts = _plate_points(0.095)
    region = Region("lid", box_mm=((-50, -30, 1), (50, 30, 3)))
    inp = judge(
        nominal,
        pts,
        TOL,
        regions=[region],
        uncertainty_mm=np.full(len(pts), 0.01),
        decision=DecisionRule("guarded", ambiguous="fail"),
    )
    r = summarise(inp)["region_verdicts"][0]
    assert r["verdict"] == "fail" and r["n_out_of_tolerance"] == 0 and r["n_ambiguous"] == 60


def test_cloud_ply_carries_u_and_a_rebuilt_report_judges_the_same(tmp_path: Path) -> None:
    nominal, pts = _plate_points(0.105)
    u = np.linspace(0.005, 0.02, len(pts))
    rule = DecisionRule("guarded")
    doc = write_report(tmp_path, judge(nominal, pts, TOL, uncertainty_mm=u, decision=rule), pictures=False)
    codes = read_ply_field(tmp_path / "cloud.ply", "uncertainty")
    assert codes is not None and codes.dtype == np.uint16  # 2 bytes a point (docs/storage.md)
    stored = decode_uncertainty(codes)
    assert np.all(stored >= u - 1e-12) and np.all(stored - u < 1e-4 + 1e-12)  # 0.1 um steps, rounded up
    assert np.isnan(decode_uncertainty(encode_uncertainty(np.array([np.nan, 1.0]))))[0]
    again = summarise(
        judge(nominal, read_ply_points(tmp_path / "cloud.ply"), TOL, uncertainty_mm=stored, decision=rule)
    )
    assert again["decision"]["counts"] == doc["decision"]["counts"] and again["verdict"] == doc["verdict"]
    assert doc["uncertainty"]["U_mm"]["max"] == pytest.approx(0.04, abs=1e-6)
    assert doc["uncertainty"]["target_U_mm"] == pytest.approx(0.05)


def _recipe(tmp_path: Path, **extra: object) -> Path:
    trimesh.creation.box(extents=PLATE).export(tmp_path / "plate.stl")
    doc = {"part": {"cad": "plate.stl"}, "tolerance": {"lower": -0.1, "upper": 0.1}, **extra}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    return tmp_path / "r.yaml"


def test_recipe_decision_fields(tmp_path: Path) -> None:
    r = load_recipe(_recipe(tmp_path))
    assert r.decision_rule == "simple" and r.guard_band.k == 2.0 and r.guard_band.ambiguous == "incomplete"
    r = load_recipe(_recipe(tmp_path, decision_rule="guarded", guard_band={"k": 3, "ambiguous": "fail"}))
    assert (r.decision_rule, r.guard_band.k, r.guard_band.ambiguous) == ("guarded", 3.0, "fail")
    with pytest.raises(ConfigError, match="decision_rule"):
        load_recipe(_recipe(tmp_path, decision_rule="strict"))
    with pytest.raises(ConfigError, match="guard_band.ambiguous"):
        load_recipe(_recipe(tmp_path, decision_rule="guarded", guard_band={"ambiguous": "maybe"}))


def test_report_page_shows_the_u_map_the_classes_and_the_ambiguous_areas(tmp_path: Path) -> None:
    nominal, pts = _plate_points(0.105)
    inp = judge(
        nominal,
        pts,
        TOL,
        min_defect_points=10,
        uncertainty_mm=np.full(len(pts), 0.01),
        decision=DecisionRule("guarded"),
        uncertainty={"decode_mm": {"median": 0.01, "p95": 0.01, "max": 0.01}, "pose_mm": None},
    )
    doc = write_report(tmp_path, inp, pictures=True)
    page = (tmp_path / "report.html").read_text()
    assert "Uncertainty and decision" in page and page.count("view of U") == 4
    assert "ambiguous-1" in page and "views' poses, after the alignment" in page
    assert doc["decision"]["counts"] == {"conform": len(pts) - 60, "ambiguous": 60, "nonconform": 0}
