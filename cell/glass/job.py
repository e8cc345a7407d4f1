"""One glass inspection end to end on a rig: calibrate (or load) the view vectors, grab, measure, error map
and report into a run folder. The rig is injected (the ``cell glass`` command builds the simulated one).

Run folder (cell/runs.py layout): ``inputs/`` copies of recipe, rig config and meshes; ``views/`` the averaged
frame of each camera, stored losslessly (:mod:`cell.glass.grabs`: ``<camera>.png``, ``grabs.json``);
``calibration/`` the view-vector calibrations used (when computed in this run); ``results/`` the report files
of the lambertian inspection (report.json/html, cloud.ply with ``deviation``) for the accepted points in the
part frame, their measured normals in cloud.ply too (``nx ny nz``), and ``glass_points.npz`` with every
measured point (world frame, accepted or not) and its rejection figures.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.analysis.errormap import NominalMesh
from cell.analysis.judge import judge
from cell.analysis.report import Tolerance, write_report
from cell.contracts import GlassRig, MarkerScreen
from cell.errors import CalibrationError, ConfigError
from cell.geometry import invert, transform_points
from cell.glass.calibration import ViewVectorCalibration, calibrate_view_vectors
from cell.glass.config import GlassRecipe, GlassRigConfig
from cell.glass.grabs import save_grab
from cell.glass.inspect import GlassMeasurement, measure
from cell.glass.surface import SmoothSurface
from cell.runs import RunFolder

BoardPlacer = Callable[[float | None], None]
ScreenMover = Callable[[int], MarkerScreen]  # moves the screen to position 0 or 1, returns it there


def grab_mean(rig: GlassRig, frames: int) -> list[NDArray[np.float32]]:
    """Mean of ``frames`` simultaneous grabs, one float32 image per camera (averaging cuts the noise)."""
    acc = [f.pixels.astype(np.float64) for f in rig.grab_all(5000.0)]
    for _ in range(frames - 1):
        acc = [a + f.pixels for a, f in zip(acc, rig.grab_all(5000.0))]
    return [(a / frames).astype(np.float32) for a in acc]


def calibrate_rig(
    rig: GlassRig, cfg: GlassRigConfig, place_board: BoardPlacer, frames: int
) -> list[ViewVectorCalibration]:
    """Vector calibration of every camera (2.6): the board at its two heights, ``frames`` grabs averaged."""
    boards = []
    for h in cfg.board.heights_mm:
        place_board(h)
        boards.append(grab_mean(rig, frames))
    place_board(None)
    return [
        calibrate_view_vectors((boards[0][k], boards[1][k]), cfg.board, cam)
        for k, cam in enumerate(cfg.cameras)
    ]


def load_calibrations(directory: Path, cfg: GlassRigConfig) -> list[ViewVectorCalibration] | None:
    """The latest saved calibration of every camera in ``directory``, or None if any camera has none."""
    try:
        cals = [ViewVectorCalibration.load(directory, cam.name) for cam in cfg.cameras]
    except CalibrationError:
        return None
    for cal, cam in zip(cals, cfg.cameras):
        if cal.serial != cam.serial or tuple(cal.resolution) != (cam.width_px, cam.height_px):
            raise CalibrationError(
                f"{directory}: the calibration of '{cam.name}' is for serial {cal.serial} at "
                f"{cal.resolution}, the rig has {cam.serial} at {(cam.width_px, cam.height_px)}; "
                "recalibrate into an empty calibration_dir"
            )
    return cals


def inspect_glass(
    recipe_path: Path,
    out: Path,
    rig_path: Path | None,
    sim_actual: Path | None,
    frames: int,
    board_frames: int,
    method: str | None,
    place_board: BoardPlacer,
) -> tuple[RunFolder, dict[str, Any]]:
    """``cell glass``: load the recipe (``method`` overrides its search method) and the rig config
    (``rig_path``, default the recipe's), create the run folder ``out`` with copies of every input, build the
    rig (the simulated one renders ``sim_actual``, default the recipe's ``part.actual``, else the nominal)
    and run :func:`run_glass_inspection`. Returns the run folder and the summary."""
    from cell.devices import build_glass_rig
    from cell.glass.config import load_glass_recipe, load_glass_rig
    from cell.mesh import load_mesh

    rec = load_glass_recipe(recipe_path)
    if method is not None:
        if method not in ("golden_section", "multi_projection"):
            raise ConfigError(f"--method {method!r}: use golden_section or multi_projection", field="method")
        rec.search.method = method  # type: ignore[assignment]
    rig_path = rig_path or rec.rig
    cfg = load_glass_rig(rig_path)
    if rec.search.method == "multi_projection" and cfg.screen.second_T_W_S is None:
        raise ConfigError(
            "the multi-projection method needs the screen's second known position: add "
            "screen.second_T_W_S to the rig config",
            path=str(rig_path),
            field="screen",
        )
    T_W_P = rec.part.T_W_P.matrix()
    nominal_W = load_mesh(rec.part.cad, what="nominal pane").apply_transform(T_W_P)
    actual_path = sim_actual or rec.part.actual or rec.part.cad
    actual_W = load_mesh(actual_path, what="simulated actual pane").apply_transform(T_W_P)
    part = rec.name or rec.part.cad.stem
    run = RunFolder.create(out.parent, part, name=out.name)
    inputs = (
        (recipe_path, "recipe.yaml"),
        (rig_path, "rig.yaml"),
        (rec.part.cad, "nominal" + rec.part.cad.suffix),
        (actual_path, "actual" + Path(actual_path).suffix),
    )
    for src, name in inputs:
        run.copy_input(Path(src), name)
    run.log("run_created", part=part, recipe=str(recipe_path), rig=str(rig_path), actual=str(actual_path))
    rig, place, move_screen = build_glass_rig(cfg, actual_W, place_board)
    return run, run_glass_inspection(run, rec, cfg, rig, place, nominal_W, frames, board_frames, move_screen)


def run_glass_inspection(
    run: RunFolder,
    recipe: GlassRecipe,
    cfg: GlassRigConfig,
    rig: GlassRig,
    place_board: BoardPlacer,
    nominal_W: trimesh.Trimesh,
    frames: int = 4,
    board_frames: int = 8,
    move_screen: ScreenMover | None = None,
) -> dict[str, Any]:
    """Calibrate or load, grab, measure and report; returns the summary (verdict, counts, statistics).
    The multi-projection method (``recipe.search.method``) also grabs with the screen moved by
    ``move_screen`` to its second position."""
    t0 = time.monotonic()
    multi = recipe.search.method == "multi_projection"
    if multi and (move_screen is None or cfg.screen.second_T_W_S is None):
        raise ConfigError(
            "the multi-projection method needs a rig that moves its screen to a second known "
            "position: set screen.second_T_W_S in the rig config (simulated rig only)",
            field="search.method",
        )
    rig.connect()
    try:
        cal_dir = recipe.calibration_dir
        cals = load_calibrations(cal_dir, cfg) if cal_dir is not None else None
        source = f"loaded from {cal_dir}"
        if cals is None:
            cals = calibrate_rig(rig, cfg, place_board, board_frames)
            cal_dir = cal_dir or run.path / "calibration"
            for cal in cals:
                cal.save(cal_dir)
            source = f"calibrated in this run, saved to {cal_dir}"
        run.log("calibration", source=source, model_rms_px=[c.meta.get("model_rms_px") for c in cals])
        screen = rig.screen
        images = grab_mean(rig, frames)
        second = None
        if multi and move_screen is not None:
            screen2 = move_screen(1)
            second = (grab_mean(rig, frames), screen2)
            move_screen(0)
    finally:
        rig.close()
    for cam, img in zip(cfg.cameras, images):
        save_grab(run.path / "views", cam.name, img, frames)
    run.log("grabbed", cameras=len(images), frames=frames)
    if second is not None:
        for cam, img in zip(cfg.cameras, second[0]):
            save_grab(run.path / "views", f"{cam.name}.screen2", img, frames)
    m = measure(images, cals, SmoothSurface(nominal_W), screen, recipe.search, second=second)
    run.log("measured", points=len(m.points), accepted=int(m.accepted.sum()))
    return _report(
        run,
        recipe,
        nominal_W,
        m,
        {
            "calibration": source,
            "frames": frames,
            "cameras": [c.name for c in cfg.cameras],
            "seconds": round(time.monotonic() - t0, 2),
        },
    )


def _report(
    run: RunFolder, recipe: GlassRecipe, nominal_W: trimesh.Trimesh, m: GlassMeasurement, meta: dict[str, Any]
) -> dict[str, Any]:
    T_P_W = invert(recipe.part.T_W_P.matrix())
    nominal = NominalMesh.from_trimesh(nominal_W.copy().apply_transform(T_P_W))
    acc = m.accepted
    pts_P = transform_points(T_P_W, m.points[acc])
    normals_P = m.normals[acc] @ T_P_W[:3, :3].T
    unconfirmed = (m.n_cameras < 2) & ~m.single_projection  # depth rests on the CAD normal
    inconsistent = ~unconfirmed & ~acc & (m.p_value <= recipe.search.outlier_alpha)
    excluded = {
        "unconfirmed_single_camera": int(unconfirmed.sum()),
        "inconsistent_normals": int(inconsistent.sum()),
        "depth_uncertain": int((~acc & ~unconfirmed & ~inconsistent).sum()),
    }
    metadata = {
        "part": recipe.name or recipe.part.cad.stem,
        "cad": str(recipe.part.cad),
        "method": "back-imaging glass (reflection search seeded by the CAD, multi-camera feedback, "
        "chi-square consistency test; single-camera multi-projection points by their two-screen fit)",
        "search_method": recipe.search.method,
        "markers": int(len(m.points)),
        "accepted": int(acc.sum()),
        "normal_sigma_urad": round(m.normal_sigma_rad * 1e6, 2),
        "depth_sigma_median_mm": float(np.median(m.depth_sigma_mm[acc])) if acc.any() else None,
        **meta,
    }
    r = run.results_dir
    inp = judge(
        nominal,
        pts_P,
        Tolerance(recipe.tolerance.lower, recipe.tolerance.upper),
        n_points_input=len(m.points),
        excluded=excluded,
        link_radius_mm=glass_link_radius_mm(m.points[acc], m.camera[acc]) or None,
        metadata=metadata,
        point_fields={f"n{k}": np.asarray(normals_P[:, i], np.float64) for i, k in enumerate("xyz")},
    )
    doc = write_report(r, inp)
    np.savez_compressed(
        r / "glass_points.npz",
        points_W=m.points,
        normals_W=m.normals,
        accepted=acc,
        camera=m.camera,
        dot=m.dot,
        n_cameras=m.n_cameras,
        p_value=m.p_value,
        depth_sigma_mm=m.depth_sigma_mm,
        points_single_W=m.points_single,
        single_projection=m.single_projection,
    )
    summary = {
        "verdict": doc["verdict"],
        "n_points": doc["n_points"],
        "markers": int(len(m.points)),
        "deviation": doc["deviation"],
    }
    run.log("reported", **summary)
    return summary


def glass_link_radius_mm(
    points: NDArray[np.float64], camera: NDArray[np.int64], factor: float = 1.5
) -> float:
    """Link radius (mm) for grouping out-of-tolerance glass points into regions: ``factor`` x the median
    nearest-neighbour spacing within one camera's points (one point per marker). The report's default, 3x
    the spacing of the merged cloud, is set by the near-coincident points of different cameras and splits
    one defect into many regions."""
    gaps = [
        np.asarray(cKDTree(points[camera == c]).query(points[camera == c], k=2)[0])[:, 1]
        for c in np.unique(camera)
        if np.sum(camera == c) > 1
    ]
    return factor * float(np.median(np.concatenate(gaps))) if gaps else 0.0
