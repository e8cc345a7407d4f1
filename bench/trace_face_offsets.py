"""Where a box face's offset in bench/study_uncertainty.py's worlds comes from, against the simulator's truth,
without rendering (issue 17: the +y face's +0.1 mm in all 30 worlds; docs/uncertainty.md).

A geometric model of each view: points on the true box faces -> the true camera pixel and projector column
(the world's lenses, projector pose, hand-eye, kinematics) -> the calibrated sensor's ray/column-plane
triangulation -> the believed camera pose -> error along the face's outward normal. No decode noise and no
alignment: the +y face's offset after the 3-2-1 alignment on the -y wall is the box's width error, the sum of
the outward errors of the +y view (0) and the -y view (2). Per seed of a study folder it prints

* ``measured``: the study's +y face offset (study.json, when analysed) and ``model``: this model's;
* ``sensor``: the same with the true camera poses (the calibrated sensor alone), ``poses``: with the true
  sensor and the believed poses (the kinematic and hand-eye calibration alone);
* ``refits``: the kinematics routine's views fitted again (cell.calibration.kinematics.fit_kinematics) with
  the world's true lens, from (a) the detected corners, (b) the exact corners, (c) the exact corners moved by
  each view's mean detected error only; the +y width error each gives with the true sensor;
* with ``--views``: how alike the seeds' kinematics views are: the correlation between seeds of the views'
  mean corner errors (detected minus the truth's projection).

    .venv/bin/python bench/trace_face_offsets.py --study DIR --seeds 1-6 [--views]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cell.calibration.kinematics import BoardObservation, KinematicErrors, fit_kinematics  # noqa: E402
from cell.config import CellConfig, load_cell_config, load_recipe  # noqa: E402
from fakes.sim.world import World, build_world, place_about  # noqa: E402

Pair = tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray
]  # K_cam, dist_cam, K_proj, dist_proj, T_C_P
FACES = {"+x": (0, 1, 60.0), "-x": (0, -1, -60.0), "+y": (1, 1, 45.0), "-y": (1, -1, -45.0)}  # box of tests/


def project(K: np.ndarray, dist: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of points (N, 3) in a device's frame: OpenCV's Brown model."""
    out = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(dist, float))[0]
    return np.asarray(out, float).reshape(-1, 2)


def column(pair: Pair, X_C: np.ndarray) -> np.ndarray:
    """The projector column (px) lighting camera-frame points ``X_C`` (N, 3)."""
    T = pair[4]
    return project(pair[2], pair[3], (X_C - T[:3, 3]) @ T[:3, :3])[:, 0]


def triangulate(pair: Pair, px: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Camera-frame points where ``pair``'s camera ray through ``px`` meets its projector column ``u``."""
    xy = cv2.undistortPoints(px.reshape(-1, 1, 2), pair[0], pair[1], None, None, None, (3, 50, 1e-15))
    ray = np.column_stack([np.asarray(xy, float).reshape(-1, 2), np.ones(len(px))])
    za, zb = np.full(len(ray), 370.0), np.full(len(ray), 410.0)  # secant on the depth
    fa, fb = column(pair, ray * za[:, None]) - u, column(pair, ray * zb[:, None]) - u
    for _ in range(40):
        same = fb == fa
        zc = np.where(same, zb, zb - fb * (zb - za) / np.where(same, 1.0, fb - fa))
        za, fa, zb = zb, fb, zc
        fb = column(pair, ray * zb[:, None]) - u
    return ray * zb[:, None]


class Seed:
    """One seed of a study folder: its cell, world, calibration and run."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        s = folder.name.removeprefix("seed")
        self.cfg: CellConfig = load_cell_config(folder / f"cell_seed{s}.yaml")
        self.world: World = build_world(self.cfg)
        c, p = self.world.sensor.camera, self.world.sensor.projector
        self.true: Pair = (
            c.K(),
            c.distortion.as_array(),
            p.K(),
            self.world.projector_distortion,
            p.T_C_P.matrix(),
        )
        a = np.load(folder / "calibration" / "projector" / "projector.npz")
        self.cal: Pair = (a["camera_K"], a["camera_dist"], a["K"], a["dist"], a["T_C_P"])
        recipe = load_recipe(folder / f"box_seed{s}.yaml")
        T_W_P = recipe.part.T_W_P.matrix()
        centre = trimesh.load(folder / f"box_dent_seed{s}.stl").apply_transform(T_W_P).bounds.mean(axis=0)
        self.T_W_Ptrue = place_about(self.world.placement, centre) @ T_W_P
        self.T_W_B = self.cfg.robot.T_W_B.matrix()

    def true_camera(self, q: np.ndarray) -> np.ndarray:
        return self.T_W_B @ self.world.true_flange(q) @ self.world.sensor.T_T_C.matrix()

    def faces(
        self, pair: Pair, believed: Callable[[np.ndarray, dict], np.ndarray]
    ) -> dict[tuple[str, str], float]:
        """Mean outward error (mm) of each (view, face) the run's views see."""
        out = {}
        for vd in sorted((self.folder / "run" / "views").iterdir()):
            v = json.loads((vd / "view.json").read_text())
            q = np.asarray(v["joints_rad"])
            Tb, Tt = believed(q, v), self.true_camera(q)
            for name, (ax, sign, at) in FACES.items():
                a, z = np.meshgrid(np.linspace(-0.9, 0.9, 25), np.linspace(3.0, 38.0, 25))
                P = np.zeros((a.size, 3))
                P[:, ax], P[:, 1 - ax], P[:, 2] = at, a.ravel() * (60.0 if ax == 1 else 45.0), z.ravel()
                n = self.T_W_Ptrue[:3, :3] @ np.eye(3)[ax] * sign
                XW = P @ self.T_W_Ptrue[:3, :3].T + self.T_W_Ptrue[:3, 3]
                XC = (XW - Tt[:3, 3]) @ Tt[:3, :3]
                sight = XW - Tt[:3, 3]
                px, u = project(self.true[0], self.true[1], XC), column(self.true, XC)
                ok = (sight @ n < -0.3 * np.linalg.norm(sight, axis=1)) & (u > 2) & (u < 1021)
                ok &= (px[:, 0] > 2) & (px[:, 0] < 510) & (px[:, 1] > 2) & (px[:, 1] < 382)
                if ok.sum() >= 100:
                    X = triangulate(pair, px[ok], u[ok]) @ Tb[:3, :3].T + Tb[:3, 3]
                    out[(vd.name, name)] = float(np.mean((X - XW[ok]) @ n))
        return out

    def width_y(self, pair: Pair, believed: Callable[[np.ndarray, dict], np.ndarray]) -> float:
        f = self.faces(pair, believed)
        return f[("000", "+y")] + f[("002", "-y")]

    def kinematics_views(self, corners: str) -> tuple[list[BoardObservation], np.ndarray]:
        """The kinematics routine's views with ``corners``: detected, exact (the true camera's projection of
        the board), or view_mean (exact moved by each view's mean detected error)."""
        run = self.folder / "calibration" / "kinematics"
        plan = next(json.loads(line) for line in open(run / "journal.jsonl") if '"plan"' in line)["views"]
        cam = self.world.sensor.camera
        obs, first = [], None
        for vd in sorted((run / "views").iterdir()):
            v, d = json.loads((vd / "view.json").read_text()), np.load(vd / "data.npz")
            q, T_W_Bd = np.asarray(v["joints"]), np.asarray(plan[int(vd.name)]["T_W_Bd"])
            Tt = self.true_camera(q)
            obj = d["object_mm"]
            exact = project(
                cam.K(),
                cam.distortion.as_array(),
                (obj @ T_W_Bd[:3, :3].T + T_W_Bd[:3, 3] - Tt[:3, 3]) @ Tt[:3, :3],
            )
            seen = d["corners_px"].reshape(-1, 2)
            c = {"detected": seen, "exact": exact, "view_mean": exact + (seen - exact).mean(axis=0)}[corners]
            obs.append(BoardObservation(q, c, obj))
            first = d["T_C_Bd"] if first is None else first
        assert first is not None
        return obs, first

    def refit_width(self, corners: str) -> float:
        """+y width error (true sensor), the kinematics refitted from ``corners`` through the true lens."""
        cam = self.world.sensor.camera
        obs, first = self.kinematics_views(corners)
        fit = fit_kinematics(obs, cam.K(), cam.distortion.as_array(), self.cfg.sensor.T_T_C.matrix(), first)
        errors = KinematicErrors(fit.errors.dd, fit.errors.da, fit.errors.dq)
        return self.width_y(self.true, lambda q, v: self.T_W_B @ errors.flange(q) @ fit.T_T_C)

    def view_mean_errors(self) -> np.ndarray:
        obs, _ = self.kinematics_views("detected")
        exact, _ = self.kinematics_views("exact")
        return np.concatenate(
            [(o.corners_px - e.corners_px).mean(axis=0) for o, e in zip(obs, exact, strict=True)]
        )


def seeds_of(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", type=Path, required=True, help="a bench/study_uncertainty.py --out folder")
    ap.add_argument("--seeds", default="1-6")
    ap.add_argument("--views", action="store_true", help="also correlate the seeds' kinematics views")
    args = ap.parse_args()
    study = args.study / "study.json"
    measured = (
        {r["seed"]: r["face_offsets_mm"]["+y"] for r in json.loads(study.read_text())["per_seed"]}
        if study.exists()
        else {}
    )
    rows: list[dict[str, Any]] = []
    means = []
    for s in seeds_of(args.seeds):
        seed = Seed(args.study / f"seed{s}")
        believed = lambda q, v: np.asarray(v["T_W_C"])  # noqa: E731
        true_pose = lambda q, v, seed=seed: seed.true_camera(q)  # noqa: E731
        row = {
            "seed": s,
            "measured": measured.get(s),
            "model": round(seed.width_y(seed.cal, believed), 4),
            "sensor": round(seed.width_y(seed.cal, true_pose), 4),
            "poses": round(seed.width_y(seed.true, believed), 4),
            "refits": {c: round(seed.refit_width(c), 4) for c in ("detected", "exact", "view_mean")},
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.views:
            means.append(seed.view_mean_errors())
    for key in ("model", "sensor", "poses"):
        x = np.array([r[key] for r in rows])
        print(f"{key}: mean {x.mean():+.4f} mm, sd {x.std():.4f} mm over {len(x)} seeds")
    if means:
        corr = np.corrcoef(np.array(means))
        off = corr[~np.eye(len(corr), dtype=bool)]
        print(f"views' mean corner errors, correlation between seeds: {off.min():.2f} to {off.max():.2f}")


if __name__ == "__main__":
    main()
