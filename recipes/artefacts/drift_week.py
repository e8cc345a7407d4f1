"""A simulated week of start-of-shift checks with a slow drift injected into the world: the projector turns
slowly on the sensor bar (the world's ``camera_projector`` rotation grows by ``--step-deg`` a day, every other
world error zero), and ``cell verify check`` runs once a day into one runs root. Shows when the drift
warning fires against when SD exceeds its MPE (docs/verification.md).

Run ``.venv/bin/python recipes/artefacts/drift_week.py --runs DIR [--days 7] [--step-deg 0.004]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
ZERO = {"translation_mm": 0.0, "rotation_deg": 0.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, required=True, help="runs root (created)")
    ap.add_argument("--days", type=int, default=7)
    ap.add_argument("--step-deg", type=float, default=0.004, help="projector rotation per day, deg")
    ap.add_argument("--cell", type=Path, default=REPO / "recipes" / "cells" / "sim.yaml")
    args = ap.parse_args()
    args.runs.mkdir(parents=True, exist_ok=True)
    base = yaml.safe_load(args.cell.read_text())
    for day in range(args.days):
        cfg = dict(base)
        cfg["world"] = {
            "seed": 1,
            "hand_eye": ZERO,
            "camera_projector": {"translation_mm": 0.0, "rotation_deg": day * args.step_deg},
            "camera": {"focal_fraction": 0.0, "principal_point_px": 0.0},
            "projector": {"focal_fraction": 0.0, "principal_point_px": 0.0},
            "projector_distortion": {},
            "robot": {"link_length_mm": 0.0, "joint_zero_deg": 0.0, "repeatability_mm": 0.0},
            "placement": ZERO,
            "microstructure": False,
        }
        path = args.runs / f"cell-day{day}.yaml"
        path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        print(f"--- day {day}: projector turned {day * args.step_deg:.3f} deg", flush=True)
        cmd = [sys.executable, "-m", "cell", "verify", "check", "--cell", str(path), "--runs", str(args.runs)]
        subprocess.run(cmd, check=False)


if __name__ == "__main__":
    main()
