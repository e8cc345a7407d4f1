"""The planner against the simulator's ground truth (renderer hit/lit masks), the simulated robot, and
bad input. The feedback steps run in :func:`run_loop`, the controller's evaluate/replan sequence without
devices, so the planner is judged on the truth alone (no decoding, no pose refinement)."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.config import DEFAULT_CELL, MaterialConfig, load_cell_config, load_recipe
from cell.errors import ConfigError
from cell.geometry import Pose
from cell.planning.feedback import FeedbackPlanner, evaluate, select_new
from cell.planning.measured import MeasuredView
from cell.planning.planner import Plan, plan_initial, plan_recipe
from cell.planning.settings import PlanSettings
from cell.planning.viewpoints import Viewpoint
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene
from fakes.sim_cell import build_sim_cell
from tests.truth_model import measure_from_truth

ROOT = Path(__file__).resolve().parent.parent
CFG = load_cell_config(DEFAULT_CELL)


def small_camera_cfg(f: int = 4):
    """Same field of view with 1/f of the pixels: keeps ground-truth renders fast."""
    cam = CFG.sensor.camera
    cam2 = cam.model_copy(
        update=dict(
            width_px=cam.width_px // f,
            height_px=cam.height_px // f,
            fx_px=cam.fx_px / f,
            fy_px=cam.fy_px / f,
            cx_px=(cam.cx_px + 0.5) / f - 0.5,
            cy_px=(cam.cy_px + 0.5) / f - 0.5,
        )
    )
    return CFG.model_copy(update=dict(sensor=CFG.sensor.model_copy(update=dict(camera=cam2))))


def truth_measure(mesh, material):
    cfg = small_camera_cfg()
    r = SceneRenderer(cfg.sensor, cfg.sim, Scene.from_meshes(mesh, cfg.sim, material))
    return lambda T: measure_from_truth(r.ground_truth(T), T, cfg, material)


@dataclass
class LoopResult:
    """Every viewpoint measured (in order), their measurements and the coverage per iteration."""

    viewpoints: list[Viewpoint]
    views: list[MeasuredView]
    coverage: list[float]


def run_loop(plan: Plan, measure: Callable[[Pose], MeasuredView]) -> LoopResult:
    """Measure the plan's viewpoints, then evaluate and replan with the functions the inspection's evaluating
    and replanning steps call (evaluate, propose, select_new; unlike the job, one FeedbackPlanner carries its
    accuracy map across rounds) until Q is under the set point, the view budget or the iteration limit is
    spent, or nothing new can be proposed. Each evaluation is logged in the plan's log."""
    fb = FeedbackPlanner(plan)
    st = fb.st
    done: list[Viewpoint] = []
    views: list[MeasuredView] = []
    pending = list(plan.viewpoints)[: st.view_budget]
    coverage: list[float] = []
    ia = np.zeros((0, 3))
    for k in range(st.max_iterations + 1):
        new = [measure(v.T_W_C) for v in pending]
        done += pending
        views += new
        ev = evaluate(fb, views, len(views) - len(new), ia)
        ia = ev.ia
        coverage.append(ev.coverage)
        plan.log.append(
            {
                "event": "evaluate",
                "views": len(done),
                "coverage": ev.coverage,
                "glare_regions": sum(r.reason == "glare" for mv in new for r in mv.defects),
            }
        )
        if ev.qualified or len(done) >= st.view_budget or k == st.max_iterations:
            break
        pending = select_new(fb, fb.propose(k, new, ev.covered, ev.ia), [d.T_W_C for d in done])
        if not pending:
            break
    return LoopResult(done, views, coverage)


@pytest.fixture(scope="module")
def pillar_plan():
    return plan_recipe(ROOT / "recipes/pillar.yaml", DEFAULT_CELL)


def test_pillar_plan_covers_the_part_in_the_simulator(pillar_plan):
    plan = pillar_plan
    recipe = load_recipe(ROOT / "recipes/pillar.yaml")
    res = run_loop(plan, truth_measure(plan.surface.mesh, recipe.part.material))
    assert res.coverage[0] >= 0.95  # f0 alone, measured by the renderer's part & lit masks
    assert res.coverage[-1] >= 0.995  # after feedback
    assert abs(res.coverage[0] - plan.coverage) < 0.03  # the prediction agrees with the measurement


def test_every_planned_pose_passes_the_simulated_robot(pillar_plan):
    from cell.planning.kinematics import UR5E
    from cell.planning.reach import sensor_body_points_T

    sim = build_sim_cell(CFG, pillar_plan.surface.mesh)
    body = sensor_body_points_T(CFG)
    for v in pillar_plan.viewpoints:
        assert sim.robot.envelope.contains(v.T_B_T[:3, 3])
        assert UR5E.reachable(v.T_B_T)[0]
        T_W_T = CFG.robot.T_W_B.matrix() @ v.T_B_T
        assert sim.robot._collision.first_contact(T_W_T[None]) is None  # the sim robot's own table/part test
        assert np.all((body @ T_W_T[:3, :3].T + T_W_T[:3, 3])[:, 2] > 0)


def test_glare_holes_are_filled_by_g_kR():
    plate = trimesh.creation.box((260, 200, 6))
    plate.apply_translation([0, 0, 3])
    glossy = MaterialConfig(albedo=0.35, specular=4.0, shininess=400.0)
    plan = plan_initial(
        plate,
        CFG,
        PlanSettings(
            aim="bisector", samples=4000, view_budget=20, max_iterations=2, q_setpoint_fraction=0.001
        ),
    )
    res = run_loop(plan, truth_measure(plate, glossy))
    first = [e for e in plan.log if e["event"] == "evaluate"]
    assert first[0]["glare_regions"] > 0 and first[0]["coverage"] < 0.995
    assert any(v.source == "g_kR" for v in res.viewpoints)
    assert res.coverage[-1] > res.coverage[0] + 0.03
    # every glare spot of the first pass is measured at the end (its nominal points lie near measured points)
    from scipy.spatial import cKDTree

    spots = np.vstack(
        [r.points_W for mv in res.views[: first[0]["views"]] for r in mv.defects if r.reason == "glare"]
    )
    measured = np.vstack([mv.points_W for mv in res.views])
    d, _ = cKDTree(measured).query(spots)
    assert np.mean(d < 2.0) > 0.99


def _recipe(tmp_path: Path, mesh: trimesh.Trimesh | None, raw: bytes | None = None) -> Path:
    stl = tmp_path / "part.stl"
    if raw is not None:
        stl.write_bytes(raw)
    else:
        mesh.export(stl)
    rec = tmp_path / "r.yaml"
    rec.write_text("part: {cad: part.stl}\ntolerance: {lower: -0.3, upper: 0.3}\n")
    return rec


@pytest.mark.parametrize(
    "case,match",
    [
        ("empty", "empty"),
        ("metres", "metres"),
        ("too_large", "larger than the working volume"),
        ("non_manifold", "non-manifold"),
    ],
)
def test_bad_cad_is_refused_and_nothing_written(tmp_path, case, match):
    from cell.cli import main

    box = trimesh.creation.box((200, 100, 40))
    box.apply_translation([0, 0, 20])
    if case == "empty":
        rec = _recipe(tmp_path, None, b"")
    elif case == "metres":
        rec = _recipe(tmp_path, box.copy().apply_scale(0.001))
    elif case == "too_large":
        rec = _recipe(tmp_path, trimesh.creation.box((3000, 500, 40)))
    else:
        fin = trimesh.Trimesh(
            np.vstack([box.vertices, [[0, 0, 200]]]),
            np.vstack([box.faces, [[box.faces[0][0], box.faces[0][1], len(box.vertices)]]]),
        )
        rec = _recipe(tmp_path, fin)
    with pytest.raises(ConfigError, match=match):
        plan_recipe(rec, DEFAULT_CELL)
    with pytest.raises(SystemExit) as ex:
        main(["plan", str(rec), "--out", str(tmp_path / "out")])
    assert ex.value.code == 2 and not (tmp_path / "out" / "plan.json").exists()


def test_cli_writes_plan_and_picture(tmp_path):
    from cell.cli import main

    box = trimesh.creation.box((180, 120, 40))
    box.apply_translation([0, 0, 20])
    rec = _recipe(tmp_path, box)
    main(["plan", str(rec), "--out", str(tmp_path / "out")])
    data = json.loads((tmp_path / "out" / "plan.json").read_text())
    assert (tmp_path / "out" / "plan.png").stat().st_size > 1000
    assert 0.8 < data["coverage"] <= 1.0 and data["planning_time_s"] > 0  # the +x face is out of reach
    assert any(e["event"] == "unreachable" for e in data["log"])
    limit = data["cycle_time"]  # the tour's motion + capture limit rides along with the plan
    assert limit["views"] == len(data["viewpoints"]) and len(limit["moves"]) == limit["views"] + 1
    assert limit["total_s"] == pytest.approx(limit["motion_s"] + limit["capture_s"])
    for v in data["viewpoints"]:
        T_W_C, T_B_T = np.array(v["T_W_C"]), np.array(v["T_B_T"])
        expect = np.linalg.inv(CFG.robot.T_W_B.matrix()) @ T_W_C @ np.linalg.inv(CFG.sensor.T_T_C.matrix())
        assert np.allclose(T_B_T, expect, atol=1e-9)
