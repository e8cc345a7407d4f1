"""Does the cell's per-point uncertainty u tell the truth, and do the decision rules decide right? (issue 17)

In the honest world (recipes/cells/sim_binned_honest.yaml: the binned camera, the simulated world differs from
the config in hand-eye, lenses, projector, robot kinematics, part placement and surface microstructure), for
each seed s: the world and the camera noise drawn from s, `cell calibrate all` of that world, then `cell
inspect` of the 120 x 90 x 40 mm box (tests/box_part.py) with a raised-cosine dent in its top face whose depth
sits near the tolerance limit (0.7-1.3 times it, in turn), aligned on six datums, judged under the guarded
rule. Then, against the simulator's truth (the dented part's own mesh in its part frame: the aligned points'
signed distance to it is their measurement error, alignment included):

* predicted u against the observed error spread, binned by u: rms(error) / rms(u) per bin;
* the verdicts of both rules (the stored cloud judged again under each) against the truth (the part is out of
  tolerance when its dent is deeper than the limit): false accepts and false rejects.

    .venv/bin/python bench/study_uncertainty.py --out DIR [--seeds 1-30] [--tolerance 0.3] [--analyse]
        [--reregister]

Each seed's calibration and run are kept in DIR and reused, so the study can be stopped and resumed; with
--analyse only the analysis runs; --reregister registers and reports every finished run again with this
checkout's code (the views, and each point's decode u in them, stay as they were measured). Prints a JSON
summary and writes DIR/study.json (docs/uncertainty.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

CELL = REPO / "recipes" / "cells" / "sim_binned_honest.yaml"
DEPTH_FACTORS = (0.7, 0.85, 0.95, 1.05, 1.15, 1.3)  # dent depth over the limit, in turn by seed
DENT_CENTRE, DENT_RADIUS = (25.0, 15.0), 12.0
# 3-2-1 datums on the box (part frame, mm): A on the top (clear of the dent), B on the -y wall, C on -x
DATUMS = [
    {"name": "A1", "point_mm": [-40.0, -30.0, 40.0]},
    {"name": "A2", "point_mm": [-40.0, 30.0, 40.0]},
    {"name": "A3", "point_mm": [45.0, -30.0, 40.0]},
    {"name": "B1", "point_mm": [-40.0, -45.0, 20.0]},
    {"name": "B2", "point_mm": [40.0, -45.0, 20.0]},
    {"name": "C1", "point_mm": [-60.0, 0.0, 20.0]},
]
MIN_BIN_POINTS = 2000  # a u bin with fewer points is reported but not judged
# the box stands on the table: its walls' lowest millimetre (part frame z < 1 mm) is where table points and
# the wall's own meet in the decode (a gross error of up to 6 mm, not a spread u describes); shown apart
SEAM_MM = 1.0


def cell_of(seed: int, folder: Path) -> Path:
    """The honest binned cell with its world and camera noise drawn from ``seed``."""
    doc = yaml.safe_load(CELL.read_text())
    doc["name"] = f"{doc['name']}-seed{seed}"
    doc["sim"]["seed"] = seed
    doc["world"]["seed"] = seed
    path = folder / f"cell_seed{seed}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def dented_box(depth_mm: float) -> trimesh.Trimesh:
    """The box of tests/box_part.py (part frame: on z = 0, centred in x, y) with a raised-cosine dent of
    ``depth_mm`` in its top face."""
    box = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=1.0)
    top = np.isclose(v[:, 2], 40.0)
    r = np.linalg.norm(v[:, :2] - np.asarray(DENT_CENTRE), axis=1)
    v[top, 2] -= depth_mm * 0.5 * (1.0 + np.cos(np.pi * np.clip(r[top] / DENT_RADIUS, 0.0, 1.0)))
    return trimesh.Trimesh(v, f, process=True)


def recipe_of(seed: int, folder: Path, tolerance: float) -> tuple[Path, float]:
    """The box recipe of ``seed`` (datums, guarded rule) and its dent depth (mm)."""
    depth = DEPTH_FACTORS[(seed - 1) % len(DEPTH_FACTORS)] * tolerance
    nominal = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    nominal.apply_translation((0.0, 0.0, 20.0))
    # finer triangles: the datum alignment finds a datum's own surface among the faces near it (a 12-face
    # box has no face centre within reach of a datum: cell.analysis.alignment._own_surface comes back empty)
    v, f = trimesh.remesh.subdivide_to_size(nominal.vertices, nominal.faces, max_edge=5.0)
    trimesh.Trimesh(v, f, process=True).export(folder / "box.stl")
    dented_box(depth).export(folder / f"box_dent_seed{seed}.stl")
    recipe = {
        "name": f"box-seed{seed}",
        "part": {
            "cad": "box.stl",
            "actual": f"box_dent_seed{seed}.stl",
            "T_W_P": {"xyz_mm": [0.0, -60.0, 0.0]},
        },
        "tolerance": {"lower": -tolerance, "upper": tolerance},
        "min_coverage": 0.6,
        "plan": {"resolution_mm": 1.5, "point_density_per_mm2": 0.2, "view_budget": 10, "max_iterations": 1},
        "alignment": {"method": "datums", "datums": DATUMS},
        "decision_rule": "guarded",
        "guard_band": {"k": 2.0, "ambiguous": "incomplete"},
    }
    path = folder / f"box_seed{seed}.yaml"
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    return path, depth


def cell_cmd(*args: str) -> bool:
    """Run ``cell ARGS`` (this checkout), niced; exit codes 0/4/5 (pass, fail, incomplete) are verdicts. A
    failed command is printed and the study goes on with the next seed."""
    cmd = ["nice", "-n", "10", sys.executable, "-m", "cell", *args]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
    if proc.returncode not in (0, 4, 5):
        print(f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
        return False
    return True


def reregister(run_dir: Path) -> None:
    """Register and report a finished run again with this checkout's code (views as measured)."""
    from cell.inspection import LambertianInspection
    from cell.inspection_run import load_run_inputs, open_inspection_run
    from cell.mesh import load_mesh
    from cell.run_data import Checkpoint

    run = open_inspection_run(run_dir)
    recipe, cfg, _ = load_run_inputs(run)
    print(f"{run_dir}: pose prior {pose_prior(run_dir)}", flush=True)
    nominal_W = load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
    job = LambertianInspection(recipe, cfg, nominal_W)
    job.settings.pictures = False
    job.report(run, job.register(run, Checkpoint.from_json(run.load_checkpoint()).views))
    job.render(run)  # cloud.ply (the analysis reads it) is written after the verdict


def pose_prior(run_dir: Path) -> list[float]:
    """``robot.pose_uncertainty_mm/deg`` as the run's own cell config gives it (its inputs/ copy, read with
    this checkout's schema and defaults): the pose prior a re-registration assumes with a kinematic
    calibration."""
    from cell.inspection_run import load_run_inputs, open_inspection_run

    robot = load_run_inputs(open_inspection_run(run_dir))[1].robot
    return [robot.pose_uncertainty_mm, robot.pose_uncertainty_deg]


def run_seed(seed: int, out: Path, tolerance: float) -> dict[str, Any]:
    """Calibrate the world of ``seed`` and inspect its box (each reused when already done)."""
    folder = out / f"seed{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    cell = cell_of(seed, folder)
    calibrated = folder / "calibration" / "cell.yaml"
    t0 = time.perf_counter()
    if not calibrated.is_file() and not cell_cmd(
        "calibrate", "all", "--cell", str(cell), "--out", str(folder / "calibration")
    ):
        return {"seed": seed, "failed": "calibration"}
    t1 = time.perf_counter()
    recipe, depth = recipe_of(seed, folder, tolerance)
    run = folder / "run"
    if not (run / "results" / "report.json").is_file():
        cell_cmd("inspect", str(recipe), "--cell", str(calibrated), "--out", str(run))
    t2 = time.perf_counter()
    return {"seed": seed, "depth_mm": depth, "calibrate_s": round(t1 - t0, 1), "inspect_s": round(t2 - t1, 1)}


def read_cloud(path: Path) -> dict[str, np.ndarray]:
    from cell.analysis.report_files import read_ply_field, read_ply_points

    fields = {k: read_ply_field(path, k) for k in ("deviation", "uncertainty", "isolated")}
    return {"points": read_ply_points(path), **{k: v for k, v in fields.items() if v is not None}}


def analyse_seed(seed: int, out: Path, tolerance: float) -> dict[str, Any]:
    """Errors against the truth and the verdicts of both rules of one seed's run."""
    from cell.analysis.decision import DecisionRule
    from cell.analysis.errormap import NominalMesh, signed_distance
    from cell.analysis.judge import judge
    from cell.analysis.regions import Tolerance
    from cell.analysis.report import summarise
    from cell.analysis.report_files import decode_uncertainty

    folder = out / f"seed{seed}"
    depth = DEPTH_FACTORS[(seed - 1) % len(DEPTH_FACTORS)] * tolerance
    cloud = read_cloud(folder / "run" / "results" / "cloud.ply")
    actual = NominalMesh.from_trimesh(trimesh.load(folder / f"box_dent_seed{seed}.stl"))
    nominal = NominalMesh.from_trimesh(trimesh.load(folder / "box.stl"))
    judged = cloud["isolated"] == 0 if "isolated" in cloud else np.ones(len(cloud["points"]), bool)
    pts, u = cloud["points"], decode_uncertainty(cloud["uncertainty"])
    error = signed_distance(actual, pts).deviation_mm
    verdicts = {}
    for rule in ("simple", "guarded"):
        inp = judge(
            nominal,
            pts,
            Tolerance(-tolerance, tolerance),
            min_defect_points=10,
            uncertainty_mm=u,
            decision=DecisionRule(rule, 2.0, "incomplete"),
        )
        verdicts[rule] = summarise(inp)["verdict"]
    report = json.loads((folder / "run" / "results" / "report.json").read_text())
    steps = json.loads((folder / "calibration" / "calibration.json").read_text())["steps"]
    plane = steps.get("validate", {}).get("summary", {}).get("plane", {})
    return {
        "validation_height_error_mm": plane.get("height_error_mm"),
        "seed": seed,
        "depth_mm": round(depth, 5),
        "out_of_tolerance": bool(depth > tolerance),
        "verdicts": verdicts,
        "report_verdict": report["verdict"],
        "pose_prior_mm_deg": pose_prior(folder / "run"),
        "pose_u_p95_mm": report["uncertainty"]["budget"]["pose_mm"]["p95"],
        "error": error[judged],
        "u": u[judged],
        "seam": pts[judged, 2] < SEAM_MM,
        "face": face_of(pts[judged]),
        "n_points": int(judged.sum()),
        "views": len(report.get("metadata", {}).get("views", [])),
        "table_seam_points": report.get("excluded", {}).get("table_seam_points"),
        "sphere_radius_error_mm": steps.get("validate", {})
        .get("summary", {})
        .get("sphere", {})
        .get("radius_error_mm"),
    }


FACES = ("top", "+x", "-x", "+y", "-y")


def face_of(points: np.ndarray) -> np.ndarray:
    """Index into FACES of the box face each point (part frame) lies on, len(FACES) for none (the dent's rim,
    edges)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    tests = (z > 39.5, x > 59.5, x < -59.5, y > 44.5, y < -44.5)
    face = np.full(len(points), len(FACES))
    for k, t in reversed(list(enumerate(tests))):
        face[t] = k
    return face


def face_offsets(r: dict[str, Any]) -> dict[str, float]:
    """One seed's mean error (mm) of each box face, off the seam."""
    out = {}
    for k, name in enumerate(FACES):
        m = (r["face"] == k) & ~r["seam"]
        if m.any():
            out[name] = round(float(r["error"][m].mean()), 4)
    return out


def by_face(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per box face over the seeds: rms(error) / rms(u), and the face's offset (its mean error in each seed:
    on a face one view measured, mostly that view's pose error as the alignment leaves it, one draw a seed)
    as rms over the seeds against the rms of the face's u: a test of u with as many independent draws as
    seeds, where a bin of points has only as many as the views in it."""
    out = []
    for k, name in enumerate(FACES):
        e = [r["error"][(r["face"] == k) & ~r["seam"]] for r in results]
        u = [r["u"][(r["face"] == k) & ~r["seam"]] for r in results]
        e_all, u_all = np.concatenate(e), np.concatenate(u)
        offsets = np.array([x.mean() for x in e if len(x)])
        rms_u = float(np.sqrt(np.mean(u_all**2)))
        out.append(
            {
                "face": name,
                "points": int(len(e_all)),
                "rms_u_mm": round(rms_u, 5),
                "rms_error_mm": round(float(np.sqrt(np.mean(e_all**2))), 5),
                "ratio": round(float(np.sqrt(np.mean(e_all**2))) / rms_u, 3),
                "offset_rms_over_seeds_mm": round(float(np.sqrt(np.mean(offsets**2))), 5),
                "offset_mean_over_seeds_mm": round(float(offsets.mean()), 5),
            }
        )
    return out


def bins_by_u(u: np.ndarray, error: np.ndarray, n_bins: int = 8) -> list[dict[str, Any]]:
    """rms(error) / rms(u) in bins of equal point counts of u."""
    edges = np.quantile(u, np.linspace(0, 1, n_bins + 1))
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (u >= lo) & (u <= hi)
        rms_e, rms_u = float(np.sqrt(np.mean(error[m] ** 2))), float(np.sqrt(np.mean(u[m] ** 2)))
        out.append(
            {
                "u_mm": [round(float(lo), 5), round(float(hi), 5)],
                "points": int(m.sum()),
                "rms_u_mm": round(rms_u, 5),
                "rms_error_mm": round(rms_e, 5),
                "mean_error_mm": round(float(np.mean(error[m])), 5),
                "ratio": round(rms_e / rms_u, 3),
                "judged": bool(m.sum() >= MIN_BIN_POINTS),
            }
        )
    return out


def decisions(results: list[dict[str, Any]]) -> dict[str, Any]:
    """False accepts (out of tolerance, passed) and false rejects (in tolerance, failed; and not passed) per
    rule."""
    out: dict[str, Any] = {}
    bad = [r for r in results if r["out_of_tolerance"]]
    good = [r for r in results if not r["out_of_tolerance"]]
    for rule in ("simple", "guarded"):
        out[rule] = {
            "parts_out_of_tolerance": len(bad),
            "false_accepts": sum(r["verdicts"][rule] == "pass" for r in bad),
            "parts_in_tolerance": len(good),
            "false_rejects_fail": sum(r["verdicts"][rule] == "fail" for r in good),
            "not_accepted": sum(r["verdicts"][rule] != "pass" for r in good),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", default="1-30", help="a range a-b or a comma list")
    ap.add_argument("--tolerance", type=float, default=0.3, help="symmetric tolerance, mm")
    ap.add_argument("--analyse", action="store_true", help="only analyse the runs already made")
    ap.add_argument("--reregister", action="store_true", help="register and report the runs again first")
    args = ap.parse_args()
    if "-" in args.seeds:
        a, b = (int(x) for x in args.seeds.split("-"))
        seeds = list(range(a, b + 1))
    else:
        seeds = [int(x) for x in args.seeds.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    timings = []
    if not args.analyse:
        for s in seeds:
            timings.append(run_seed(s, args.out, args.tolerance))
            print(json.dumps(timings[-1]), flush=True)
    done = [s for s in seeds if (args.out / f"seed{s}" / "run" / "results" / "report.json").is_file()]
    if args.reregister:
        for s in done:
            reregister(args.out / f"seed{s}" / "run")
    results = [analyse_seed(s, args.out, args.tolerance) for s in done]
    u = np.concatenate([r["u"] for r in results])
    e = np.concatenate([r["error"] for r in results])
    seam = np.concatenate([r["seam"] for r in results])

    summary = {
        "cell": str(CELL.relative_to(REPO)),
        "tolerance_mm": args.tolerance,
        "seeds": done,
        "points": int(len(u)),
        "overall": {
            "rms_u_mm": round(float(np.sqrt(np.mean(u**2))), 5),
            "rms_error_mm": round(float(np.sqrt(np.mean(e**2))), 5),
            "mean_error_mm": round(float(np.mean(e)), 5),
            "share_within_2u": round(float(np.mean(np.abs(e) <= 2 * u)), 4),
        },
        "bins": bins_by_u(u, e),
        "bins_without_seam": bins_by_u(u[~seam], e[~seam]),
        "seam_points": int(seam.sum()),
        "faces": by_face(results),
        "gross_errors": {
            "points_error_over_1mm": int(np.sum(np.abs(e) > 1.0)),
            "of_which_at_the_seam": int(np.sum((np.abs(e) > 1.0) & seam)),
        },
        "per_seed": [
            {
                "seed": r["seed"],
                "depth_mm": r["depth_mm"],
                "validation_height_error_mm": r["validation_height_error_mm"],
                "verdicts": r["verdicts"],
                "report_verdict": r["report_verdict"],
                "pose_prior_mm_deg": r["pose_prior_mm_deg"],
                "pose_u_p95_mm": r["pose_u_p95_mm"],
                "views": r["views"],
                "rms_u_mm": round(float(np.sqrt(np.mean(r["u"] ** 2))), 5),
                "rms_error_mm": round(float(np.sqrt(np.mean(r["error"] ** 2))), 5),
                "table_seam_points": r["table_seam_points"],
                "sphere_radius_error_mm": r["sphere_radius_error_mm"],
                "face_offsets_mm": face_offsets(r),
            }
            for r in results
        ],
        "decisions": decisions(results),
        "timings": timings,
    }
    (args.out / "study.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "per_seed"}, indent=1))


if __name__ == "__main__":
    main()
