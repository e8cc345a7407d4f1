"""Planning feedback for recipe authors: `cell plan` warns when the predicted coverage is below the recipe's
min_coverage and names the surfaces no reachable viewpoint sees (with their CAD faces), a recipe's
exclude_from_coverage leaves faces out of planning and coverage, and an inspection's report carries the same.

The part is the box of tests/box_part.py placed 200 mm further from the robot's base (at y = -400 mm) than
where every face is in reach: its +y face then faces away from the robot. Which faces those are is read from
the mesh itself (normals), independently of the planner."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cell.config import DEFAULT_CELL, load_recipe
from cell.errors import ConfigError
from cell.planning.planner import plan_recipe
from cell.planning.unseen import face_ranges, plan_feedback
from tests.box_part import write_box_recipe

FAR_MM = (0.0, 200.0, 0.0)  # the box's +y face is out of the robot's reach here
FAST = {"min_patch_area_mm2": 1500, "samples": 5000}  # an unreachable face is split into few patches


def _recipe(folder: Path, **changes) -> Path:
    path = write_box_recipe(folder, FAR_MM)
    data = yaml.safe_load(path.read_text())
    data["min_coverage"] = 0.95
    data["plan"].update(FAST)
    data.update(changes)
    path.write_text(yaml.safe_dump(data))
    return path


def _far_faces(folder: Path) -> set[int]:
    """The box's +y face, from the mesh: the faces whose normal is +y."""
    mesh = trimesh.load(folder / "box.stl", process=False)
    return {int(i) for i in np.flatnonzero(mesh.face_normals[:, 1] > 0.99)}


def test_plan_names_the_face_no_reachable_pose_sees_and_warns(tmp_path: Path, capsys) -> None:
    from cell.cli import main

    recipe = _recipe(tmp_path)
    far = _far_faces(tmp_path)
    plan = plan_recipe(recipe, DEFAULT_CELL)
    feedback = plan_feedback(plan, load_recipe(recipe))
    (unseen,) = feedback.unseen
    assert set(unseen.faces) == far and unseen.facing() == "+y"
    assert unseen.area_mm2 == pytest.approx(120 * 40, rel=0.05)  # the face's area, to the sampling error
    assert unseen.centre_mm[1] == pytest.approx(45.0, abs=0.5)  # part frame: the face is at y = +45 mm
    assert plan.coverage < 0.95 and len(feedback.warnings) == 1
    main(["plan", str(recipe), "--out", str(tmp_path / "out")])  # a warning, not an error: it returns
    err = capsys.readouterr().err
    assert "warning: the plan predicts" in err and "below the recipe's min_coverage of 95.0%" in err
    assert "facing +y" in err and f"exclude_from_coverage: [{', '.join(map(str, sorted(far)))}]" in err
    doc = json.loads((tmp_path / "out" / "plan.json").read_text())
    assert doc["min_coverage"] == 0.95 and set(doc["unseen_surfaces"][0]["faces"]) == far


def test_excluded_faces_leave_planning_and_coverage(tmp_path: Path) -> None:
    ref = plan_recipe(_recipe(tmp_path), DEFAULT_CELL)
    far = _far_faces(tmp_path)
    excluded = _recipe(tmp_path, exclude_from_coverage=sorted(far))
    plan = plan_recipe(excluded, DEFAULT_CELL)
    feedback = plan_feedback(plan, load_recipe(excluded))
    assert plan.coverage > 0.99 and feedback.unseen == [] and feedback.warnings == []
    assert plan.surface.inspectable_area_mm2 == pytest.approx(
        ref.surface.inspectable_area_mm2 - 120 * 40, rel=0.02
    )
    (entry,) = [e for e in plan.log if e["event"] == "excluded"]
    assert entry["faces"] == len(far) and entry["area_mm2"] == pytest.approx(120 * 40, rel=0.05)
    assert not any(np.isin(plan.surface.face[plan.surface.inspectable], sorted(far)))


def test_an_excluded_face_the_cad_lacks_is_refused(tmp_path: Path) -> None:
    recipe = _recipe(tmp_path, exclude_from_coverage=[3, 12])
    with pytest.raises(ConfigError, match="field 'exclude_from_coverage'") as info:
        plan_recipe(recipe, DEFAULT_CELL)
    assert "face 12 does not exist" in str(info.value) and "12 faces" in str(info.value)


def test_face_ranges_are_compact() -> None:
    assert face_ranges([9, 3, 7, 8, 12]) == "3, 7-9, 12"
    assert face_ranges(list(range(0, 40, 2)), max_ranges=3) == "0, 2, 4 and 17 more range(s)"


def test_the_report_carries_the_unseen_surfaces(tmp_path: Path) -> None:
    """The inspection's report step on the far box measured on its top only (no views: nothing more is
    needed to judge): incomplete, and the report names the face and says why."""
    from cell.inspection import LambertianInspection
    from cell.mesh import load_mesh
    from cell.runs import RunFolder
    from tests.box_part import small_cell

    recipe = load_recipe(_recipe(tmp_path))
    nominal_W = load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
    job = LambertianInspection(recipe, small_cell(), nominal_W)
    job.settings.pictures = False
    run = RunFolder.create(tmp_path, "box", name="run")
    xy = np.random.default_rng(1).uniform((-60, -45), (60, 45), (20000, 2))
    np.save(run.results_dir / "points_P.npy", np.c_[xy, np.full(len(xy), 40.0)])
    assert job.report(run, {})["verdict"] == "incomplete"
    report = json.loads((run.results_dir / "report.json").read_text())
    unseen = report["metadata"]["plan"]["unseen_surfaces"]
    assert set(unseen[0]["faces"]) == _far_faces(tmp_path) and unseen[0]["facing"] == "+y"
    assert any("no reachable viewpoint sees P" in w and "facing +y" in w for w in report["warnings"])
