"""Trace the camera calibration's focal-length error in the honest world, one candidate at a time.

Renders the intrinsics routine's ChArUco views with the world's true camera (fakes.sim.board, as the simulated
board stage does), detects them with the pipeline's detector and calibrates with the pipeline's
calibrateCamera call, and compares with the world's truth (bench code may read it; cell/ may not):

- the corner detector's error: each detected corner against the true projection of the board corner
  (world camera, true board pose): mean, RMS and its radial part (a radial bias is what scales fx);
- the calibrated fx against the world's, and OpenCV's own standard deviation of fx (the noise it expects).

Switches take one simulator effect away at a time (noise, camera defocus, texture anti-aliasing): not to make
the figure pass, but to see which one the error follows.

    .venv/bin/python bench/trace_intrinsics.py --seed 1 --views 12 [--no-noise] [--no-blur] [--model rational]
"""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np

from cell.calibration.intrinsics import REFINE_SIGMA_PX, CharucoView, calibrate_intrinsics, refine_corners
from cell.calibration.procedures import CHARUCO, charuco, charuco_poses
from cell.config import DEFAULT_CELL, load_cell_config
from fakes.sim.board import board_texture, render_textured_board
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene
from fakes.sim.world import build_world


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--pose-seed", type=int, default=None, help="board poses' seed (default: --seed)")
    ap.add_argument("--no-noise", action="store_true")
    ap.add_argument("--no-blur", action="store_true", help="camera focused everywhere (f-number 1e6)")
    ap.add_argument(
        "--raw", action="store_true", help="the CharucoDetector's corners as they come (no refine_corners)"
    )
    ap.add_argument("--sigma", type=float, default=REFINE_SIGMA_PX, help="refine_corners' smoothing (px)")
    ap.add_argument("--flags", default="fix_k3", help="fix_k3 | free_k3 | rational | thin_prism")
    ap.add_argument("--ideal", action="store_true", help="the ideal world's camera (the config's)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    cfg = load_cell_config(DEFAULT_CELL)
    world = build_world(cfg.model_copy(update={"world": "ideal" if args.ideal else cfg.world}))
    if not args.ideal:
        data = cfg.world if isinstance(cfg.world, dict) else {}
        world = build_world(cfg.model_copy(update={"world": {**data, "seed": args.seed}}))
    sensor = world.sensor
    if args.no_blur:
        sensor = sensor.model_copy(update={"camera": sensor.camera.model_copy(update={"f_number": 1e6})})
    sim = cfg.sim.model_copy(update={"noise": not args.no_noise})
    cam = sensor.camera
    renderer = SceneRenderer(sensor, sim, Scene.from_meshes(None, sim), projector_distortion=None)
    board = charuco(CHARUCO)
    tex, ppm = board_texture(board)
    rng = np.random.default_rng(args.seed if args.pose_seed is None else args.pose_seed)
    poses = charuco_poses(CHARUCO, cfg.sensor.standoff_mm, args.views, rng)
    noise = np.random.default_rng(100 + args.seed)
    K_true = cam.K()
    d_true = cam.distortion.as_array()
    views, errs, radial = [], [], []
    for T in poses:
        img = render_textured_board(renderer, T, tex, ppm, noise)
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(img)
        if ids is None or len(ids) < 8:
            continue
        found = CharucoView(corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int32))
        if not args.raw:
            found = refine_corners(img, found, board, sigma_px=args.sigma)
        views.append(found)
        obj = found.object_points(board)
        true_px, _ = cv2.projectPoints(obj, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K_true, d_true)
        e = found.corners_px - true_px.reshape(-1, 2)
        errs.append(e)
        r = found.corners_px - (cam.cx_px, cam.cy_px)
        radial.append(np.sum(e * r, axis=1) / np.maximum(np.linalg.norm(r, axis=1), 1e-9))
    e = np.concatenate(errs)
    rad = np.concatenate(radial)
    flags = {
        "fix_k3": cv2.CALIB_FIX_K3,
        "free_k3": 0,
        "rational": cv2.CALIB_RATIONAL_MODEL,
        "thin_prism": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL,
    }[args.flags]
    obj = [v.object_points(board).astype(np.float32).reshape(-1, 1, 3) for v in views]
    img = [v.corners_px.astype(np.float32).reshape(-1, 1, 2) for v in views]
    rms, K, dist, _, _, std_intr, _, _ = cv2.calibrateCameraExtended(
        obj, img, (cam.width_px, cam.height_px), None, None, flags=flags
    )
    if args.flags == "fix_k3":  # the pipeline's own call, as a check that this script matches it
        pipe = calibrate_intrinsics(views, board, (cam.width_px, cam.height_px))
        assert abs(pipe.K[0, 0] - K[0, 0]) < 1e-6
    out = {
        "seed": args.seed,
        "views": len(views),
        "corners": int(len(e)),
        "corner_err_mean_px": e.mean(axis=0).round(4).tolist(),
        "corner_err_rms_px": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
        "corner_err_radial_mean_px": float(rad.mean()),
        "rms_px": float(rms),
        "fx_err_pct": float(100 * (K[0, 0] / cam.fx_px - 1)),
        "fy_err_pct": float(100 * (K[1, 1] / cam.fy_px - 1)),
        "fx_std_pct": float(100 * std_intr[0, 0] / K[0, 0]),
        "cx_err_px": float(K[0, 2] - cam.cx_px),
        "cy_err_px": float(K[1, 2] - cam.cy_px),
        "dist": np.asarray(dist).ravel()[:5].round(5).tolist(),
        "dist_true": d_true.round(5).tolist(),
    }
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k}: {v}")


if __name__ == "__main__":
    main()
