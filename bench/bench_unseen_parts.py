"""Whole inspections of parts the planner was never tuned on: verdict, coverage, views and wall time each.

Run: .venv/bin/python bench/bench_unseen_parts.py [--cell recipes/cells/sim_binned.yaml] [--out DIR]

The parts are generated here (trimesh primitives, mm, standing on the table) and rendered as their own
nominal, so a correct cell says ``pass`` wherever it can measure enough of the surface and ``incomplete``
where this robot placement cannot see it (surfaces facing the table or facing away from the robot).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
import yaml

REPO = Path(__file__).resolve().parent.parent


def _bracket() -> trimesh.Trimesh:
    """An L-section bracket 120 x 80 mm, 15 mm thick, 60 mm tall."""
    outline = np.array([(0, 0), (120, 0), (120, 15), (15, 15), (15, 80), (0, 80)], float)
    mesh = trimesh.creation.extrude_triangulation(
        outline, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]]), 60.0
    )
    return mesh.apply_translation(-mesh.bounds.mean(0) + [0, 0, 30.0])


def _dome() -> trimesh.Trimesh:
    """A spherical cap of radius 70 mm, 50 mm high, on the table."""
    radius, centre_z = 70.0, -20.0
    t = np.linspace(np.pi / 2, np.arcsin(-centre_z / radius), 40)
    profile = np.vstack([np.c_[radius * np.cos(t), centre_z + radius * np.sin(t)], [0.0, 0.0]])
    profile[0, 0] = 0.0
    return trimesh.creation.revolve(profile[::-1], sections=96)


def _parts() -> dict[str, tuple[trimesh.Trimesh, dict]]:
    torus = trimesh.creation.torus(major_radius=60, minor_radius=15, major_sections=96, minor_sections=32)
    bar = trimesh.creation.cylinder(radius=40, height=400, sections=128)
    bar.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    tiny = trimesh.creation.box(extents=(20, 15, 8))
    return {
        "bracket": (_bracket(), {"xyz_mm": [40, -30, 0], "rpy_deg": [0, 0, 35]}),
        "dome": (_dome(), {"xyz_mm": [-20, 10, 0], "rpy_deg": [0, 0, 0]}),
        "torus": (torus.apply_translation((0, 0, 15)), {}),
        "bar": (bar.apply_translation((0, 0, 40)), {}),
        "tiny": (tiny.apply_translation((0, 0, 4)), {}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell", type=Path, default=REPO / "recipes" / "cells" / "sim_binned.yaml")
    ap.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temporary folder)")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="unseen-"))
    out.mkdir(parents=True, exist_ok=True)
    print("| part | triangles | verdict | coverage | views | views skipped | wall s |")
    print("|---|---|---|---|---|---|---|")
    for name, (mesh, pose) in _parts().items():
        mesh.export(out / f"{name}.stl")
        recipe = {
            "name": name,
            "part": {"cad": f"{name}.stl", "T_W_P": pose or {"xyz_mm": [0, 0, 0], "rpy_deg": [0, 0, 0]}},
            "tolerance": {"lower": -0.2, "upper": 0.2},
        }
        (out / f"{name}.yaml").write_text(yaml.safe_dump(recipe))
        run = out / f"run_{name}"
        t0 = time.monotonic()
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "cell",
                "inspect",
                str(out / f"{name}.yaml"),
                "--cell",
                str(args.cell),
                "--out",
                str(run),
            ],
            capture_output=True,
            text=True,
            cwd=REPO,
        )
        wall = time.monotonic() - t0
        if proc.returncode != 0:
            print(f"| {name} | {len(mesh.faces)} | error (exit {proc.returncode}) | | | | {wall:.1f} |")
            continue
        doc = json.loads((run / "results" / "report.json").read_text())
        skipped = (run / "journal.jsonl").read_text().count("view skipped")
        print(
            f"| {name} | {len(mesh.faces)} | {doc['verdict']} | {100 * doc['coverage']:.1f} % | "
            f"{len(doc['metadata']['views'])} | {skipped} | {wall:.1f} |"
        )
    print(f"\nruns in {out}")


if __name__ == "__main__":
    main()
