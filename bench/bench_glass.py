"""Glass rig: time per marker search, a whole pane (thousands of markers), and error against cameras (1-4).

Run: .venv/bin/python bench/bench_glass.py [--rig recipes/glass/rig_sim.yaml] [--repeats 3]

Renders the sagged test pane (recipes/glass/pane.yaml, truth in recipes/glass/panes/pane_sag.truth.json) on
the rig once, calibrates its view vectors, averages 4 frames per camera, then times the pieces. The machine
is shared, so each timing is the best of ``--repeats`` runs; wall and process CPU time are printed with the
load average. Errors are z(measured) - z(actual pane) in mm; "accepted" = passed cell/glass/consistency.py.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from cell.glass.config import load_glass_recipe, load_glass_rig
from cell.glass.inspect import GlassMeasurement, find_markers, measure, screen_point_W
from cell.glass.job import calibrate_rig, grab_mean
from cell.glass.reflection import RaySearchProblem, ReflectionLaw, exhaustive, golden_section, stepwise
from cell.glass.surface import SmoothSurface
from cell.mesh import load_mesh
from fakes.glass_rig import SimGlassRig
from fakes.sim.glass_pane import sag_height, windshield_height

GLASS = Path(__file__).resolve().parent.parent / "recipes" / "glass"


def best_of(fn, repeats: int):  # any callable, its result
    """Best wall and CPU time (s) of ``repeats`` calls, and the last result."""
    wall, cpu, out = np.inf, np.inf, None
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return wall, cpu, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", type=Path, default=GLASS / "rig_sim.yaml")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, python "
        f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f}"
    )
    recipe = load_glass_recipe(GLASS / "pane.yaml")
    truth = json.loads((GLASS / "panes" / "pane_sag.truth.json").read_text())
    sag = sag_height(
        windshield_height(truth["radius_x_mm"], truth["radius_y_mm"]),
        truth["sag_depth_mm"],
        tuple(truth["sag_centre_mm"]),
        truth["sag_sigma_mm"],
    )

    def err_of(g: GlassMeasurement) -> np.ndarray:
        return g.points[:, 2] - sag(g.points[:, 0], g.points[:, 1])

    cfg = load_glass_rig(args.rig)
    cad = SmoothSurface(load_mesh(recipe.part.cad))
    t = time.perf_counter()
    rig = SimGlassRig(cfg, load_mesh(recipe.part.actual))
    rig.connect()
    cals = calibrate_rig(rig, cfg, rig.place_board, frames=8)
    images = grab_mean(rig, 4)
    print(
        f"rig {cfg.name}: {len(cfg.cameras)} cameras {cfg.cameras[0].width_px}x{cfg.cameras[0].height_px}; "
        f"render + calibration {time.perf_counter() - t:.1f} s\n"
    )

    s = recipe.search
    screen = rig.screen
    m = find_markers(images[0], cals[0], cad, screen, s)
    ok = (m.dot >= 0) & np.all(np.isfinite(m.dirs), axis=1)
    law = ReflectionLaw(RaySearchProblem(m.origins[ok], m.dirs[ok], screen_point_W(screen, m.dot[ok])), cad)
    n = int(ok.sum())
    print(f"## Marker search, camera {cfg.cameras[0].name}: {n} markers\n")
    print("| search | wall ms/marker | CPU ms/marker | theta evaluations/marker (median, max) |")
    print("|---|---|---|---|")
    tol = s.angle_tol_urad * 1e-6
    runs = {
        "golden section (2.3.4)": lambda: golden_section(law, s.max_surface_error_mm, tol, s.length_tol_mm),
        "step-wise (2.3.3)": lambda: stepwise(law, 0.1, tol, s.length_tol_mm),
    }
    sub = np.arange(min(n, 200))
    sub_law = ReflectionLaw(RaySearchProblem(law.p.origins[sub], law.p.dirs[sub], law.p.markers[sub]), cad)
    runs["exhaustive, 1 um steps (200 markers)"] = lambda: exhaustive(sub_law, s.max_surface_error_mm, 1e-3)
    for name, fn in runs.items():
        wall, cpu, res = best_of(fn, args.repeats if "exhaustive" not in name else 1)
        k = len(res.t)
        print(
            f"| {name} | {1e3 * wall / k:.3f} | {1e3 * cpu / k:.3f} | {int(np.median(res.iterations))}, "
            f"{int(res.iterations.max())} |"
        )

    wall, cpu, full = best_of(lambda: measure(images, cals, cad, screen, s), args.repeats)
    print(
        f"\n## Whole pane, feedback until the normal settles ({s.feedback_tol_urad:g} urad): "
        f"{len(full.points)} markers from {len(images)} cameras in {wall:.2f} s wall, {cpu:.2f} s CPU "
        f"({1e3 * wall / len(full.points):.2f} ms/marker); {int(full.accepted.sum())} accepted, RMS "
        f"{np.sqrt(np.mean(err_of(full)[full.accepted] ** 2)):.3f} mm\n"
    )

    print("## Error against the number of cameras (feedback forced to use them all)\n")
    print(
        "RMS all: every marker; RMS accepted: the points this run's consistency test accepts; "
        f"RMS common: the markers the {len(images)}-camera run accepts (the same set in every row).\n"
    )
    print(
        "| cameras | points | RMS all | accepted | RMS accepted | median abs accepted | p99 abs accepted | "
        "RMS common | time (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    rows = {
        c: best_of(lambda c=c: measure(images, cals, cad, screen, s, max_cameras=c), 1)
        for c in range(len(images), 0, -1)
    }
    common = rows[len(images)][2].accepted
    for c in sorted(rows):
        wall, _, g = rows[c]
        err = err_of(g)
        a = g.accepted
        fmt = (lambda v: f"{v:.3f}") if a.any() else (lambda v: "-")
        ea = np.abs(err[a]) if a.any() else np.zeros(1)
        print(
            f"| {c} | {len(err)} | {np.sqrt(np.mean(err**2)):.3f} | {int(a.sum())} | "
            f"{fmt(np.sqrt(np.mean(ea**2)))} | {fmt(np.median(ea))} | {fmt(np.percentile(ea, 99))} | "
            f"{np.sqrt(np.mean(err[common] ** 2)):.3f} | {wall:.2f} |"
        )

    if cfg.screen.second_T_W_S is None:
        return
    print("\n## Multi-projection (2.4) against golden section: the screen moved to its second position\n")
    screen2 = rig.move_screen(1)
    images2 = grab_mean(rig, 4)
    rig.move_screen(0)
    mp = s.model_copy(update={"method": "multi_projection"})
    print("| method | cameras | RMS all | accepted | RMS accepted | wall s (incl. detection) |")
    print("|---|---|---|---|---|---|")
    for c in (1, len(images)):
        for name, search, second in (
            ("golden section", s, None),
            ("multi-projection", mp, (images2, screen2)),
        ):
            wall, _, g = best_of(
                lambda search=search, second=second, c=c: measure(
                    images, cals, cad, screen, search, max_cameras=c, second=second
                ),
                1,
            )
            err, a = err_of(g), g.accepted
            rms_a = f"{np.sqrt(np.mean(err[a] ** 2)):.4f}" if a.any() else "-"
            print(
                f"| {name} | {c} | {np.sqrt(np.mean(err**2)):.3f} | {int(a.sum())} | {rms_a} | {wall:.2f} |"
            )


if __name__ == "__main__":
    main()
