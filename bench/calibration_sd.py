"""What a calibration alone does to the VDI/VDE 2634 Part 2 figures: SD and PS per ball-bar position, and
the plane's form, from noise-free correspondences (simulation bench: it reads the world's truth, cell/ never
does).

For every artefact position of Part 2 (cell/verification/positions.py, the volume of the true camera), points
on the surface the camera sees are projected through the world's true camera and projector (lens distortion
included) to their pixel and projector column, then triangulated with the calibrated model (the cell config's
active calibration: camera K and distortion, projector K, distortion and T_C_P), exactly as the pinhole
triangulator does but at the exact sub-pixel position. Sphere and plane fits are the verification's. What it
leaves out: decoding noise, the sensor's filters, the artefact's placement error. So the figures are the
calibration's share of SD and PS, to compare calibrations in seconds instead of one acceptance run each.

    .venv/bin/python bench/calibration_sd.py CAL/cell.yaml [CAL2/cell.yaml ...] [--json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.calibration.active import active_sensor_config
from cell.config import CellConfig, SensorConfig, load_cell_config
from cell.verification.certificate import load_certificate
from cell.verification.figures import fit_plane, fit_sphere
from cell.verification.positions import Volume, ball_bar_positions, plane_positions
from fakes.sim.world import World, build_world

CERTIFICATE = Path(__file__).resolve().parents[1] / "recipes" / "artefacts" / "certificate.yaml"


def observe(true: SensorConfig, proj_dist: NDArray, X_C: NDArray) -> tuple[NDArray, NDArray]:
    """Camera pixel (N, 2) and projector column (N,) of points ``X_C`` (true camera frame, mm)."""
    cam, proj = true.camera, true.projector
    px, _ = cv2.projectPoints(X_C, np.zeros(3), np.zeros(3), cam.K(), cam.distortion.as_array())
    T_P_C = np.linalg.inv(proj.T_C_P.matrix())
    X_P = X_C @ T_P_C[:3, :3].T + T_P_C[:3, 3]
    pp, _ = cv2.projectPoints(X_P, np.zeros(3), np.zeros(3), proj.K(), np.asarray(proj_dist, float))
    return px.reshape(-1, 2), pp.reshape(-1, 2)[:, 0]


def triangulate(model: SensorConfig, px: NDArray, u_p: NDArray, iterations: int = 5) -> NDArray:
    """The pinhole triangulator's arithmetic at sub-pixel positions: the camera ray of ``px`` meets the
    column plane of ``u_p``, the column corrected through the model's projector lens (mm, model camera
    frame)."""
    cam, proj = model.camera, model.projector
    xy = cv2.undistortPoints(
        px.reshape(-1, 1, 2),
        cam.K(),
        cam.distortion.as_array(),
        None,
        None,
        None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-15),
    ).reshape(-1, 2)
    ray = np.column_stack([xy, np.ones(len(xy))])
    T = proj.T_C_P.matrix()
    R, t = T[:3, :3], T[:3, 3]
    K_p, d_p = proj.K(), proj.distortion.as_array()
    T_P_C = np.linalg.inv(T)
    u = u_p.copy()
    for _ in range(iterations):
        a = (u - K_p[0, 2]) / K_p[0, 0]
        z = (R[:, 0] @ t - a * (R[:, 2] @ t)) / (ray @ R[:, 0] - a * (ray @ R[:, 2]))
        X = ray * z[:, None]
        if not np.any(d_p):
            break
        seen, _ = cv2.projectPoints(X @ T_P_C[:3, :3].T + T_P_C[:3, 3], np.zeros(3), np.zeros(3), K_p, d_p)
        u = u + (u_p - seen.reshape(-1, 2)[:, 0])
    return X


def cap(centre: NDArray, radius: float, n: int = 4000) -> NDArray:
    """Points of the sphere's half facing the camera at the origin (mm)."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(4 * n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = centre + radius * v
    facing = np.einsum("ij,ij->i", v, -p) / np.linalg.norm(p, axis=1) > 0.17  # within 80 deg
    return p[facing][:n]


def predict(cell: Path) -> dict[str, float]:
    """SD, PS (um) per ball-bar position and F (um) per plane position of the calibrated cell ``cell``."""
    cfg = load_cell_config(cell)
    return predict_model(cfg, build_world(cfg), active_sensor_config(cfg))


def predict_model(cfg: CellConfig, world: World, model: SensorConfig) -> dict[str, float]:
    """:func:`predict` for the sensor geometry ``model`` (a calibration) of the cell ``cfg`` in ``world``."""
    true = world.sensor
    cert = load_certificate(CERTIFICATE)
    bar = cert.ball_bar
    vol = Volume.of(cfg.sensor)
    V = np.array([0.0, 0.0, cfg.sensor.standoff_mm])
    out: dict[str, float] = {}
    for pos in ball_bar_positions(vol, bar.centre_distance_mm, bar.sphere_diameters_mm[0]):
        ends = [
            pos.T_V_A[:3, :3] @ [s * bar.centre_distance_mm / 2, 0, 0] + pos.T_V_A[:3, 3] + V for s in (-1, 1)
        ]
        fits = []
        for c, d in zip(ends, bar.sphere_diameters_mm, strict=True):
            X = cap(c, d / 2)
            fits.append(fit_sphere(triangulate(model, *observe(true, world.projector_distortion, X))))
        sd = np.linalg.norm(fits[0].centre - fits[1].centre) - bar.centre_distance_mm
        label = pos.label.replace("ball bar, ", "")
        out[f"SD {label}"] = 1e3 * float(sd)
        out[f"PS {label}"] = 1e3 * float(
            np.mean([f.diameter - d for f, d in zip(fits, bar.sphere_diameters_mm, strict=True)])
        )
    plane = cert.plane
    g = np.stack(
        np.meshgrid(
            np.linspace(-0.48, 0.48, 49) * plane.length_mm, np.linspace(-0.4, 0.4, 11) * plane.width_mm
        ),
        -1,
    ).reshape(-1, 2)
    for pos in plane_positions(vol, plane.length_mm):
        X = np.column_stack([g, np.zeros(len(g))]) @ pos.T_V_A[:3, :3].T + pos.T_V_A[:3, 3] + V
        fit = fit_plane(triangulate(model, *observe(true, world.projector_distortion, X)), outlier_fraction=0)
        out[f"F {pos.label.replace('plane, ', '')}"] = 1e3 * fit.form_range
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cells", type=Path, nargs="+", help="calibrated cell configs (CAL/cell.yaml)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = {str(c): predict(c) for c in args.cells}
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    keys = next(iter(rows.values())).keys()
    print("| figure (um) | " + " | ".join(rows) + " |")
    print("|---|" + "---|" * len(rows))
    for k in keys:
        print(f"| {k} | " + " | ".join(f"{r[k]:+.1f}" for r in rows.values()) + " |")


if __name__ == "__main__":
    main()
