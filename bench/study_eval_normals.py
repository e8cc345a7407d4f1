"""The accuracy map's nominal normals against the simulator's surface, on a finished simulated inspection:
each paired evaluation point's normal as the evaluation takes it (its closest nominal triangle's, found with
its deviation) and as it took it before (the nearest of the plan's surface samples), each compared with the
normal of the actual part mesh the simulator rendered (the run's inputs/actual.stl, its closest triangle to
the aligned point); how often each decides the incidence check otherwise than the truth; and IA at the
recipe's and tighter tolerances with either normals (flagged points / the area ``evaluate`` counts, mm^2).

    .venv/bin/python bench/study_eval_normals.py RUN
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_tail_steps import load_finished_run  # bench/ is on sys.path when run as a script

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.geometry import incidence_cos
from cell.mesh import load_mesh
from cell.planning.feedback import MAP_LINK_MM, accuracy_map


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    args = ap.parse_args()
    run, job, checkpoint = load_finished_run(args.run)
    done = run.completed_views()
    for i in done:
        job._first_overlaps(run, job.views.get(run, i))
    evaluation = job.evaluate(run, checkpoint.views, checkpoint.iteration)
    fb, measured = evaluation.state.planner, evaluation.state.measured
    views = list(measured.values())
    pairs = job._map_pairs(run, list(measured))
    actual = NominalMesh.from_trimesh(
        load_mesh(str(args.run / "inputs/actual.stl")).apply_transform(job.T_W_P)
    )
    theta = fb.st.theta_camera_deg
    min_cos = np.cos(np.deg2rad(theta))
    angles: dict[str, list[np.ndarray]] = {"nearest sample": [], "closest triangle": []}
    wrong = dict.fromkeys(angles, 0)
    for j in range(1, len(views)):
        vj = views[j]
        used = np.zeros(len(vj.points_W), dtype=bool)
        for i in range(j):
            used[pairs(j, i, MAP_LINK_MM)[0]] = True
        points = vj.points_W[used]
        truth = actual.face_normals[signed_distance(actual, points).face]
        seen = incidence_cos(points, truth, vj.T_W_C[:3, 3]) >= min_cos
        assert vj.nominal_normals_W is not None
        for name, normals in zip(angles, (fb.normals_at(points), vj.nominal_normals_W[used]), strict=True):
            cos = np.clip(np.abs(np.einsum("ij,ij->i", normals, truth)), 0.0, 1.0)
            angles[name].append(np.rad2deg(np.arccos(cos)))
            wrong[name] += int(
                np.count_nonzero((incidence_cos(points, normals, vj.T_W_C[:3, 3]) >= min_cos) != seen)
            )
    for name, parts in angles.items():
        a = np.concatenate(parts)
        print(
            f"{name}: {len(a)} points, angle to the truth mean {a.mean():.3f} deg, max {a.max():.1f}; "
            f"> 1 deg {100 * np.mean(a > 1):.2f} %, > 5 deg {100 * np.mean(a > 5):.2f} %, > 20 deg "
            f"{100 * np.mean(a > 20):.2f} %; the {theta:g} deg incidence check otherwise than the truth's: "
            f"{wrong[name]} points"
        )
    before = [replace(v, nominal_normals_W=None) for v in views]
    surface = fb.plan.surface
    for tol in (fb.st.accuracy_tol_mm, 0.05, 0.03, 0.02, 0.015):
        found = []
        for vs in (before, views):
            ia = accuracy_map(vs, fb.normals_at, tol, max_incidence_deg=theta, pairs=pairs)
            area = float(surface.area[fb.samples_near(ia, 1.0)].sum()) if len(ia) else 0.0
            found.append(f"{len(ia)} / {area:.2f}")
        print(f"IA at {tol} mm, nearest samples' normals -> closest triangles': {found[0]} -> {found[1]}")


if __name__ == "__main__":
    main()
