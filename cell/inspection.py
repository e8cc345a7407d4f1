"""The lambertian inspection job: what the controller plans, captures, decodes, evaluates, registers, reports.

Each step reads and writes the run folder only, so any step can run again after a resume:
- plan: CAD-guided viewpoints V0 (cell.planning, chapter 3.1);
- capture: the GCLS pattern stack at one view (the robot is already there);
- decode: sub-pixel decoding, triangulation in {C}, the kinematic chain into {W} (eqs 4.1-4.4), the
  link filter (4.4), and the view's defect regions (shadow, glare, low contrast) on the nominal surface
  -> views/NNN/ (cell.view_files: points, flags, and the raw stack while the cell's retention keeps it);
- evaluate / replan: coverage, accuracy map and Q (eq 3.22) and the feedback viewpoints g_k (3.2-3.3);
- register / report: all views in the part frame, merged; signed deviations against the nominal; report.

Triangulation and hand-eye come from the cell's active calibration files (cell.calibration.active); without
them, from the cell config's nominal geometry (for the simulated cell, the simulator's truth). The report says
which.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.analysis.alignment import Aligner, AlignmentError
from cell.analysis.crop import PartCrop
from cell.analysis.decision import DecisionRule
from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.linkfilter import RIM_JUMP_MM, link_cluster, unreliable_pixels
from cell.analysis.merge import voxel_subsample_index
from cell.analysis.report import ReportInput
from cell.analysis.uncertainty import TARGET_SHARE_OF_BAND, has_view_uncertainty, view_uncertainty
from cell.analysis.view_refinement import (
    OverlapCache,
    ViewRefinement,
    estimate_normals,
    prepare_overlaps,
    refine_newest,
    refine_views,
)
from cell.calibration import (
    active_hand_eye,
    active_measuring_patterns,
    active_sensor_config,
    active_triangulator,
    believed_flange,
    calibration_residual_px,
    calibration_source,
    view_pose_prior,
)
from cell.config import CellConfig, Recipe
from cell.contracts import CameraSettings, PixelFormat, TriggerMode
from cell.controller import Controller, ControllerSettings, RobotLimits
from cell.devices import DeviceBundle
from cell.errors import ConfigError, DeviceFault
from cell.geometry import invert, transform_points, transform_vectors
from cell.inspection_results import InspectionResults, MergeBins, RegisteredCloud
from cell.inspection_views import (
    REGIONS_FILE,
    ViewResult,
    ViewStore,
    save_planes,
    save_regions,
    stored_regions,
)
from cell.planning.coverage import covered_by_views
from cell.planning.feedback import MAP_LINK_MM, FeedbackPlanner, PairCache, PairsOf, evaluate, select_new
from cell.planning.feedback import Evaluation as FeedbackEvaluation
from cell.planning.kinematics import UR5E
from cell.planning.measured import DefectRegion, MeasuredView, measured_view_from_masks
from cell.planning.motion import MotionPlanner
from cell.planning.planner import Plan, plan_initial
from cell.planning.viewpoints import Viewpoint
from cell.raycast import RayCaster
from cell.run_data import Checkpoint, Evaluation, View
from cell.runs import RunFolder, write_json_atomic
from cell.sensing.decode import Reason, decode
from cell.sensing.incidence import measured_normals
from cell.sensing.patterns import PatternSet
from cell.sensing.scan import capture_stack
from cell.sensing.stack import check_stack
from cell.sensing.triangulate import normalized_coords
from cell.view_files import (
    ViewPoints,
    decode_view_uncertainty,
    encode_view_uncertainty,
    save_raw_stack,
    save_view_points,
    stored_points,
)

# which decode reasons become which defect map of chapter 3 (IS: shadow, IR: glare)
DEFECT_REASONS = {"shadow": Reason.DARK, "glare": Reason.SATURATED, "low_contrast": Reason.LOW_CONTRAST}


@dataclass
class InspectionSettings:
    """Job-level settings (the recipe's ``plan:`` section holds the planner's)."""

    link_mm: float = 0.3  # link distance of the outlier filter (dissertation: 0.1-0.5 mm)
    min_cluster_px: int = 200
    table_margin_mm: float = 0.5  # points lower than this above the table top (world z) are the table
    crop_mm: float = 5.0  # points farther than this from the nominal surface are background, not part
    edge_jump_mm: float = RIM_JUMP_MM  # a 3x3 neighbourhood spanning more depth (or invalid) is a rim
    eval_voxel_mm: float = 0.5  # coverage and the accuracy map use one point per voxel: ample for 0.5 pt/mm^2
    merge_voxel_mm: float = 0.2  # views are averaged on this grid (quality-weighted)
    lift_mm: float = 80.0  # retract height between views
    min_defect_points: int = 10  # out-of-tolerance clusters smaller than this are isolated outliers
    pictures: bool = True


# a camera of more pixels than this decodes a view's steps one after the other: side by side, a 5 MP view's
# whole-image temporaries (its uncertainty's beside the filters', two bands of normals at once: ~0.3 GB, as
# estimated, not measured) would add to the decode's share of the hires run's peak memory (docs/benchmarks.md,
# item 5)
SIDE_BY_SIDE_MAX_PIXELS = 2_000_000


class _InOrder(Executor):
    """Runs each call as it is submitted, in the caller's thread (the decode's steps one after the other)."""

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future[Any]:
        done: Future[Any] = Future()
        try:
            done.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # raised by result(), where a side thread's would be
            done.set_exception(exc)
        return done


# a view's raw stack as save_raw_stack takes it after the folder: frames, patterns, bit depth, projector size
RawStack = tuple[NDArray[Any], PatternSet, int, tuple[int, int]]


@dataclass
class Captured:
    """One view's pattern stack and where the robot was when it was grabbed (capture -> decode)."""

    images: list[NDArray[Any]] | NDArray[Any]  # the frames, or one (N, H, W) array of them
    T_B_T: NDArray[np.float64]  # the flange pose the cell believes (cell.calibration.believed_flange)
    joints: NDArray[np.float64]
    camera: str
    index: int | None = None  # the view's index in the plan: its decode is kept in the job's view store
    # the plan's last view so far: an evaluation (and the registration beside it) waits for its decode, which
    # leaves the feedback maps' pairs of it to the evaluation (made there beside the registration, not before)
    last: bool = False
    # the view before the plan's last so far: its decode starts the joint refinement of the views up to it,
    # which the refinement after the last view begins with (LambertianInspection._start_older_ahead)
    next_to_last: bool = False


@dataclass
class FeedbackRound:
    """The feedback loop's evaluation with what it was computed from, kept for the replan that follows."""

    planner: FeedbackPlanner
    evaluation: FeedbackEvaluation
    measured: dict[int, MeasuredView]  # by view index
    alignment: str  # how the measured views were aligned for it


class LambertianInspection(InspectionResults):
    """The job the controller runs for a recipe on a structured-light cell."""

    register_while_evaluating = True  # register() may run in the controller's worker beside evaluate()

    def __init__(
        self,
        recipe: Recipe,
        cfg: CellConfig,
        nominal_W: trimesh.Trimesh,
        settings: InspectionSettings | None = None,
    ) -> None:
        self.recipe = recipe
        self.cfg = cfg
        self.nominal_W = nominal_W
        self.settings = settings or InspectionSettings()
        self.part_name = recipe.name or Path(recipe.part.cad).stem
        self.T_W_P = recipe.part.T_W_P.matrix()
        self.T_W_B = cfg.robot.T_W_B.matrix()
        self.T_T_C = active_hand_eye(cfg)
        self.sensor = active_sensor_config(cfg)  # the calibrated geometry where calibration files exist
        self.patterns: PatternSet = active_measuring_patterns(cfg)  # through the gamma LUT, if any
        self.triangulator = active_triangulator(cfg)
        # the projector's centre in {C} (mm): the incidence filter needs it only to a degree or so
        self.projector_C = self.sensor.projector.T_C_P.matrix()[:3, 3]
        self.geometry_source = calibration_source(cfg)
        # the calibration's residual as a correspondence error (px), for the points' uncertainty
        self.calibration_px, self.calibration_residual = calibration_residual_px(cfg)
        tol, guard = recipe.tolerance, recipe.guard_band
        self.decision = DecisionRule(recipe.decision_rule, guard.k, guard.ambiguous)
        self.u_target_mm = TARGET_SHARE_OF_BAND * (tol.upper - tol.lower)  # the feedback loop's target for U
        self._plan: Plan | None = None
        self._aligner: Aligner | None = None
        self._nominal_P: NominalMesh | None = None
        self.views = ViewStore()  # the completed views, each decoded or read once (cell.inspection_views)
        self._overlaps = OverlapCache()  # the refinement's matching at the views' kinematic poses, per pair
        self._pairs = PairCache()  # the feedback maps' pairs at the views' kinematic poses, per pair
        self._merge_bins: MergeBins | None = None  # the views' merge bins, made as they arrive
        self._merge_bins_lock = threading.Lock()
        self._refinement: tuple[tuple[int, ...], ViewRefinement, dict[str, Any]] | None = None
        # the joint refinement of the views but the newest, that the refinement of them all begins with
        # (:meth:`_refine`), with the prior it ran under (sigma per view: mm, rad) and its source
        self._older: tuple[tuple[int, ...], ViewRefinement, NDArray[np.float64], str] | None = None
        self._refine_lock = threading.Lock()  # one refinement at a time: a second caller waits for it
        self._refining_ahead: Future[None] | None = None  # the refinement started by the last view's decode
        self._ahead_of: ViewResult | None = None  # the view it was started for (a later start voids it)
        self._raw_later: tuple[int, RawStack] | None = None  # a raw stack written after the verdict
        self._moved: dict[bytes, dict[int, NDArray[np.float64]]] = {}  # moved eval points, by alignment
        self._cloud: RegisteredCloud | None = None  # the registration's cloud, judged ahead of the report
        # the controller may register (in its worker) while it evaluates (here): what both use is made once
        self._lock = threading.RLock()
        self._judged: tuple[ReportInput, dict[str, Any], bool] | None = None  # report input, doc, csv
        self.nominal = NominalMesh.from_trimesh(nominal_W)  # world frame, for cropping views to the part
        self._nominal_rays = RayCaster(nominal_W.vertices, nominal_W.faces, what="nominal mesh")

    # ------------------------------------------------------------------ planning
    @property
    def plan_model(self) -> Plan:
        """The f0 plan (recomputed deterministically after a resume: it also holds the surface samples)."""
        with self._lock:
            if self._plan is None:
                self._plan = plan_initial(
                    self.nominal_W, self.cfg, self.recipe.plan, self.recipe.exclude_from_coverage
                )
            return self._plan

    @staticmethod
    def _view(vp: Viewpoint, iteration: int) -> View:
        return View(vp.T_B_T, vp.T_W_C, vp.patch, vp.source, iteration)

    def motion_planner(self, speed_fraction: float) -> MotionPlanner:
        """Collision-checked paths between views against this part and the table (cell.planning.motion)."""
        robot = self.cfg.robot
        return MotionPlanner(
            self.plan_model.patch_planner.reach,
            UR5E,
            lift_mm=self.settings.lift_mm,
            z_max_mm=robot.envelope_max_mm[2] - 1.0,
            tcp_speed_mm_s=robot.max_tcp_speed_mm_s * speed_fraction,
            joint_speed_limit_rad_s=robot.max_joint_speed_rad_s,  # lines near a singularity slow down to it
        )

    def plan(self) -> list[View]:
        return [self._view(v, 0) for v in self.plan_model.viewpoints]

    # ------------------------------------------------------------------ one view
    def prepare(self, devices: DeviceBundle) -> None:
        """Camera settings for the stack: the configured trigger, the camera's native bit depth. The
        controller calls it once while connecting, so a camera that cannot do them is refused before the
        robot moves."""
        cam = self.cfg.sensor.camera
        devices.camera.configure(
            CameraSettings(
                cam.exposure_ms,
                cam.gain_db,
                PixelFormat(f"Mono{cam.bit_depth}") if cam.bit_depth != 8 else PixelFormat.MONO8,
                TriggerMode(cam.trigger),
            )
        )

    def capture(self, devices: DeviceBundle, view: View, index: int, views: Sequence[View]) -> Captured:
        """Grab view ``index``'s stack (the robot moves to every view: each lands afresh, so ``views`` are
        not needed)."""
        devices.begin_view(index)
        self.prepare(devices)
        T_B_T = believed_flange(self.cfg, devices.robot)
        joints = np.asarray(devices.robot.joints(), dtype=np.float64)
        frames = capture_stack(devices.camera, devices.projector, self.patterns)
        devices.end_view()  # a simulated cell's rendering state goes before the stack is copied
        # one array now (the list goes), not a copy of it when decoded; a stack the check will refuse stays
        images = np.stack(frames) if len({(f.shape, f.dtype) for f in frames}) == 1 else frames
        del frames
        if not devices.projector.ready():  # a lamp that failed mid-stack leaves dark frames: measure again
            status = devices.projector.status()
            why = ", ".join(status.errors) or str(status)
            raise DeviceFault(devices.projector.name, f"not ready after the pattern stack: {why}")
        last, next_to_last = index == len(views) - 1, index == len(views) - 2
        return Captured(images, T_B_T, joints, devices.camera.name, index, last, next_to_last)

    def decode(self, view: View, captured: Captured, out_dir: Path) -> dict[str, Any]:
        """Decode, triangulate and filter one view and write its folder ``out_dir`` (points, planes, holes,
        raw images while the retention keeps them); the files are written by a thread beside the compute
        (zlib and PNG encoding release the GIL), all before this returns. The raw images of the plan's last
        view (so far) are not needed for the verdict: they are kept in memory and written into its committed
        folder after the verdict (:meth:`render`), or beside the next view's decode when the feedback loop
        asks for more views (:meth:`_write_raw_later`); not on a camera decoded in order (memory)."""
        cam = self.cfg.sensor.camera
        stack = check_stack(
            captured.images,
            self.patterns,
            (cam.width_px, cam.height_px),
            cam.bit_depth,
            source=f"camera '{captured.camera}'",
        )
        captured.images = []  # the frames live on in ``stack`` only (0.4 GB for a 5 MP stack)
        in_order = stack.shape[-1] * stack.shape[-2] > SIDE_BY_SIDE_MAX_PIXELS
        later = None
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="view-files") as files:
            writes = []
            if self._raw_later is not None:  # the view before was the plan's last: more were asked for
                writes.append(files.submit(self._write_raw_later, out_dir.parent.parent))
            if self.cfg.retention.writes_raw_images:
                proj = self.cfg.sensor.projector
                raw = (stack, self.patterns, cam.bit_depth, (proj.width_px, proj.height_px))
                if captured.last and not in_order and captured.index is not None:
                    later = (captured.index, raw)
                else:
                    writes.append(files.submit(save_raw_stack, out_dir, *raw))
            with _InOrder() if in_order else ThreadPoolExecutor(1, thread_name_prefix="view-side") as side:
                summary = self._decode(captured, stack, out_dir, files, writes, side, in_order)
            for written in writes:
                written.result()  # a write that failed fails the view
        write_json_atomic(out_dir / "view.json", summary)  # last: the folder is whole once it is there
        self._raw_later = later
        return summary

    def _write_raw_later(self, run_path: Path, verdict: str | None = None) -> int:
        """Write the raw stack :meth:`decode` kept back into its view's committed folder (and forget it);
        the bytes written. Not when the view's folder is not committed (its decode or commit failed: it is
        measured again), nor when the retention keeps no raw images of a run of ``verdict`` past its end (they
        would be removed when it ends: cell.retention.apply_at_finish). A run paused, faulted or aborted
        before this writes them on its way out (:meth:`on_stop`); a killed one keeps that view whole, without
        ``raw/`` (as a view whose raw images were pruned)."""
        later, self._raw_later = self._raw_later, None
        if later is None:
            return 0
        index, raw = later
        folder = RunFolder(run_path).view_dir(index)
        if not (folder / "view.json").is_file():
            return 0
        if verdict is not None and self.cfg.retention.keep_days(verdict) == 0:
            return 0
        return save_raw_stack(folder, *raw, durable=True)

    def on_stop(self, run: RunFolder, state: str) -> dict[str, Any]:
        """The run stopped short of ``done`` (``state``: paused, faulted, aborted; the controller's
        :class:`cell.controller.Job` hook, called once its worker is idle): write the raw stack :meth:`decode`
        kept back for after the verdict into its view's folder now, durably (:meth:`_write_raw_later`), so
        that a failed run keeps its last view's raw images. Under the published verdict's retention when
        there is one (a run paused before its page), else written (no verdict yet: the run's end applies its
        retention). Returns the view and the bytes written, or ``{}``."""
        if self._raw_later is None:
            return {}
        index = self._raw_later[0]
        try:
            verdict = (Checkpoint.from_json(run.load_checkpoint()).summary or {}).get("verdict")
        except (OSError, ValueError, ConfigError):  # unreadable: kept as when no verdict is out yet
            verdict = None
        written = self._write_raw_later(run.path, verdict)
        return {"view": index, "raw_images_bytes": written} if written else {}

    def render(self, run: RunFolder) -> dict[str, Any]:
        """The report's page after its verdict (:meth:`InspectionResults.render`), then the raw images of the
        plan's last view, kept back by its decode (:meth:`_write_raw_later`)."""
        written = super().render(run)
        summary = Checkpoint.from_json(run.load_checkpoint()).summary or {}
        raw_bytes = self._write_raw_later(run.path, summary.get("verdict"))
        return written | ({"raw_images_bytes": raw_bytes} if raw_bytes else {})

    def _decode(
        self,
        captured: Captured,
        stack: NDArray[Any],
        out_dir: Path,
        files: ThreadPoolExecutor,
        writes: list[Future[Any]],
        side: Executor,
        in_order: bool,
    ) -> dict[str, Any]:
        """The view's steps (:meth:`decode`); those that only the view's results need, not the steps after
        them (its defect regions' ray casts, its points' uncertainty), run on ``side`` beside the rest (NumPy,
        OpenCV, SciPy and Embree release the GIL), the measured normals' bands on two threads, and the
        refinement after the plan's last view is started ahead: the same numbers, in less time on two cores.
        ``in_order`` (a camera of more than SIDE_BY_SIDE_MAX_PIXELS, ``side`` then runs each step as it is
        given): one step at a time, for memory."""
        cam = self.cfg.sensor.camera
        decoded = decode(stack, self.patterns, cam.bit_depth)
        cloud = self.triangulator.triangulate(decoded)
        T_W_C = self.T_W_B @ captured.T_B_T @ self.T_T_C
        defects = side.submit(self._defects, T_W_C, cloud.reasons)
        valid = cloud.valid
        kept = link_cluster(
            cloud.points_C, link_mm=self.settings.link_mm, min_cluster_px=self.settings.min_cluster_px
        )
        # the measured normals once, for the projector-incidence filter and the points' uncertainty; a code
        # without a decode uncertainty leaves the filter its own banded normals (no (H, W, 3) float64 image)
        normals = (
            measured_normals(cloud.points_C, valid, workers=1 if in_order else 2)
            if has_view_uncertainty(self.patterns)
            else None
        )
        T_C_P, fx = self.sensor.projector.T_C_P.matrix(), self.sensor.camera.fx_px
        uncertainty = side.submit(
            view_uncertainty,
            *(stack, self.patterns, decoded, cloud, T_C_P, fx, self.calibration_px, cam.bit_depth, normals),
        )
        edges, oblique = unreliable_pixels(
            cloud.points_C,
            valid,
            self.projector_C,
            self.cfg.sensor.max_projector_incidence_deg,
            self.settings.edge_jump_mm,
            normals,
        )
        del normals  # (H, W, 3) float64: 120 MB at 5 MP, freed once the uncertainty is done with it
        # points lit too obliquely stay in the view for the refinement and the feedback loop (their tens of
        # um of bias matter less there than the constraints they add: without them the ideal world's
        # refinement slid a view by 0.85 mm) but not in the measured cloud (register)
        keep = valid & kept.keep & ~edges
        points_W = transform_points(T_W_C, cloud.points_C[keep])
        quality = cloud.contrast[keep].astype(np.float32)
        oblique_kept = oblique[keep]
        crop_rule = PartCrop(0.0, self.settings.table_margin_mm, self.settings.crop_mm)
        # the table's points are cut whatever their distance from the nominal: measured off the table only
        # (a third of a view's points, and of the decode's longest step, on the demo pillar)
        off_table = ~crop_rule.on_table(points_W)
        deviation = np.zeros(len(points_W))
        deviation[off_table] = signed_distance(self.nominal, points_W[off_table]).deviation_mm
        crop = crop_rule.split(points_W, deviation)
        part = crop.part
        points_W, quality, oblique_kept = points_W[part], quality[part], oblique_kept[part]
        sub = voxel_subsample_index(points_W, self.settings.eval_voxel_mm)
        stored = stored_points(points_W)  # what the file holds and a resumed run reads
        # the view's own analysis, here in the decode worker while the robot moves on: the local planes of its
        # evaluation subset (what the multi-view refinement matches against), saved with the view (made while
        # the side thread finishes the points' uncertainty)
        eval_W = stored[sub]
        planes = estimate_normals(eval_W)
        result, run, ahead = None, RunFolder(out_dir.parent.parent), captured.last and not in_order
        if captured.index is not None:
            # the view as the job keeps it, made now with what the refinement reads (its evaluation points and
            # their planes, its pose and joints: final here) and completed below, before the store holds it
            arrived = {"T_W_C": T_W_C.tolist(), "joints_rad": captured.joints.tolist()}
            folder = run.view_dir(captured.index)  # where out_dir is renamed to
            result = ViewResult(captured.index, None, eval_W, planes, [], arrived, folder)
            if ahead:
                # the refinement the evaluation and the registration begin with, started now, beside the
                # rest of the view's steps and writes (not on a camera decoded in order: its stack is still
                # held then, at its peak memory); it makes the view's first overlaps itself
                self._forget(run, captured.index, ahead_of=result)
                self._start_refine_ahead(run, result)
        u = uncertainty.result()
        u_points = None if u is None else u.u_mm[keep][part]
        writes.append(files.submit(save_view_points, out_dir, points_W, quality, oblique_kept, sub, u_points))
        u_stored = None if u_points is None else decode_view_uncertainty(encode_view_uncertainty(u_points))
        writes.append(files.submit(save_planes, out_dir, planes))
        writes.append(files.submit(cv2.imwrite, str(out_dir / "reasons.png"), cloud.reasons))
        regions = stored_regions(defects.result())  # as a resumed run reads them
        writes.append(files.submit(save_regions, out_dir / REGIONS_FILE, regions))
        summary = {
            "T_W_C": T_W_C.tolist(),
            "T_B_T": captured.T_B_T.tolist(),
            "joints_rad": captured.joints.tolist(),
            "points": int(len(points_W)),
            "decoded": int(valid.sum()),
            "link_filtered": int((valid & ~kept.keep).sum()),
            "rim_filtered": int((valid & kept.keep & edges).sum()),
            "oblique_filtered": int(oblique_kept.sum()),
            "excluded": crop.counts(),
            "defects": {r: sum(d.reason == r for d in regions) for r in DEFECT_REASONS},
            "uncertainty": None if u is None else u.to_json(),
        }
        if result is not None:  # kept as the folder holds it: a resumed run reads the same numbers
            result.summary = json.loads(json.dumps(summary))
            result.held = ViewPoints(stored, quality, oblique_kept, u_stored)
            result.regions = regions
            result.eval_u = None if u_stored is None else u_stored[sub]
            # the plan's last view leaves its maps' pairs and its bins to the evaluation and the registration
            # (which run side by side after it): the decode both wait for is shorter
            if not ahead:
                self._first_overlaps(run, result, pair_maps=not captured.last)
            if not captured.last:
                self.bin_arrived_view(run, result)
            self.views.add(result)
            others = [v for v in self.views.completed(run) if v.index != result.index]
            # while the robot moves to the last view and captures it (not when that one is measured already:
            # this view was measured again after it)
            if captured.next_to_last and all(v.index != result.index + 1 for v in others):
                self._start_older_ahead(run, sorted([*others, result], key=lambda v: v.index))
        return summary

    def _first_overlaps(self, run: RunFolder, new: ViewResult, pair_maps: bool = True) -> None:
        """The refinement's first matching of a new view with every view measured before it (both ways, at
        their kinematic poses), and with ``pair_maps`` the feedback maps' pairs of the two
        (:meth:`_map_pairs`): what the evaluation after the last view would otherwise begin with. Whatever the
        caches held of a view of this index before (a decode that failed after this and is redone) is dropped
        first, and its merge bins (made again by :meth:`bin_arrived_view`, or when the registration first asks
        for them: the plan's last view's)."""
        self._forget(run, new.index)
        views = [v for v in self.views.completed(run) if v.index != new.index] + [new]
        prepare_overlaps(
            self._overlaps,
            [v.eval_W for v in views],
            [v.planes for v in views],
            [v.camera_W for v in views],
            [v.eval_tree if len(v.eval_W) else None for v in views],
            [v.index for v in views],
            new=len(views) - 1,
        )
        if pair_maps:
            self._pair_maps(new, views[:-1])

    def _forget(self, run: RunFolder, index: int, ahead_of: ViewResult | None = None) -> None:
        """Drop what the caches hold of view ``index`` (it is measured again): its overlaps, maps' pairs and
        merge bins, and a refinement that holds it, and the joint refinement of the views but the newest if it
        holds it (one made ahead: after it is made, as the lock orders, so that none of its overlaps of the
        earlier measurement stays in the cache). A refinement started ahead and not yet begun is void from
        here on: under the same lock, the view it is for becomes ``ahead_of`` (the one about to be started,
        else None), so an earlier start never refines a view measured again; the joint refinement of the
        views but the newest started ahead (:meth:`_start_older_ahead`) holds the lock until it is made, and
        is dropped here after it when it holds ``index`` (its cut and merge with the merge bins)."""
        with self._refine_lock:
            self._ahead_of = ahead_of
            self._overlaps.forget(index)
            self._pairs.forget(index)
            if self._refinement is not None and index in self._refinement[0]:
                self._refinement = None
                self._moved.clear()
            if self._older is not None and index in self._older[0]:
                self._older = None
        self.merge_bins_for(run).forget(index)

    def _pair_maps(self, new: ViewResult, others: Sequence[ViewResult]) -> None:
        """The feedback maps' pairs of view ``new`` with each of ``others``, both ways (:meth:`_map_pairs`),
        found now and kept (:class:`cell.planning.feedback.PairCache`)."""
        for other in others:
            for a, b in ((new, other), (other, new)):
                self._pairs.pairs(
                    a.index, b.index, MAP_LINK_MM, a.eval_W, b.eval_tree if len(b.eval_W) else None
                )

    def _defects(self, T_W_C: NDArray[np.float64], reasons: NDArray[np.uint8]) -> list[DefectRegion]:
        """Hole regions per reason, located on the nominal surface by casting their pixels' rays on the
        CAD."""
        masks = {name: (reasons & np.uint8(bit)) > 0 for name, bit in DEFECT_REASONS.items()}
        holes = np.logical_or.reduce(list(masks.values()))
        masks = {name: mask for name, mask in masks.items() if mask.any()}  # a reason no pixel has: no region
        nominal = np.full(reasons.shape + (3,), np.nan)
        if holes.any():
            cam = self.sensor.camera
            xn, yn = normalized_coords(cam.K(), cam.distortion.as_array(), cam.width_px, cam.height_px)
            rays_C = np.stack([xn[holes], yn[holes], np.ones(int(holes.sum()))], axis=-1)
            dirs = transform_vectors(T_W_C, rays_C / np.linalg.norm(rays_C, axis=1, keepdims=True))
            nominal[holes] = self._nominal_rays.first_hit_points(T_W_C[:3, 3], dirs)[1]
        empty = np.zeros(reasons.shape, dtype=bool)
        return measured_view_from_masks(T_W_C, np.zeros(reasons.shape + (3,)), empty, masks, nominal).defects

    # ------------------------------------------------------------------ feedback
    def refinement(self, run: RunFolder) -> tuple[list[int], ViewRefinement]:
        """The completed views' pose corrections against each other (cell.analysis.view_refinement), from
        their evaluation points and local planes (each view's, computed once by its decode), under the views'
        pose prior (:func:`view_pose_prior`: the kinematic calibration's, else the robot config's);
        recomputed when views were added (deterministic, so a resumed run gets the same). A refinement the
        last view's decode started (:meth:`_start_refine_ahead`) is waited for, and what failed in it raised
        here."""
        ahead = self._refining_ahead
        if ahead is not None:
            ahead.result()
        with self._refine_lock:
            return self._refine(self.views.completed(run))

    def _start_refine_ahead(self, run: RunFolder, new: ViewResult) -> None:
        """Make the refinement of the completed views and ``new``, the plan's last view so far, whose decode
        has its evaluation points and their planes (the rest of its steps and its files still to come, its
        folder not committed yet), on a thread of its own: the evaluation and the registration after it find
        it made, or wait for it (the same numbers: a function of the same views, as a resumed run reads them;
        the new view's first overlaps made in it). A view measured again meanwhile voids it
        (:meth:`_forget`, called with ``ahead_of=new`` just before this; not made when a later start or a view
        forgotten since replaced it). A daemon thread: a paused or aborted run's
        process does not wait for it (it writes nothing)."""
        done: Future[None] = Future()

        def refine() -> None:
            try:
                with self._refine_lock:
                    if self._ahead_of is new:
                        views = [v for v in self.views.completed(run) if v.index != new.index] + [new]
                        self._refine(sorted(views, key=lambda v: v.index))
            except BaseException as exc:  # raised by refinement(), to the evaluation or the registration
                done.set_exception(exc)
            else:
                done.set_result(None)

        self._refining_ahead = done
        threading.Thread(target=refine, name="refine-ahead", daemon=True).start()

    def _start_older_ahead(self, run: RunFolder, views: list[ViewResult]) -> None:
        """Make the joint refinement of ``views`` (in index order), all the views before the plan's last so
        far (the decode of the one before the last just done, or a replan that adds one view), and the
        registration's cut and merge of them (:meth:`merge_ahead`), on a thread of its own, while the robot
        moves to the last view and captures it: the refinement after the last view begins with it
        (:meth:`_refine`; the same numbers as made then: a function of the same views). The refinement lock is
        taken here and handed to the thread, which releases it when done: it comes before any other
        refinement or forgetting, whatever the threads' timing (a view measured again meanwhile is forgotten
        after it, and voids it). What fails in the refinement is left to the refinement after the last view,
        which makes it again (and raises there); a failed cut and merge is journalled. A daemon thread: a
        paused or aborted run's process does not wait for it (it writes nothing but the journal line)."""

        def refine() -> None:
            try:
                found = self._joint(views)[0] if len(views) >= 2 else None
            except Exception:  # made again (and raised) by the refinement after the last view
                found = None
            try:
                # used when the last view leaves these views' corrections as they are to the bit (it is
                # held: the demo pillar's), else the registration merges all views in full
                if found is not None:
                    self.merge_ahead(run, [v.index for v in views], found.T, found.unregistered)
            except Exception as exc:  # nothing raises it again: journalled
                run.log("error", kind="merge ahead", error=repr(exc), used=False)
            finally:
                self._refine_lock.release()

        self._refine_lock.acquire()  # released by the thread (a Lock may be released by any thread)
        try:
            threading.Thread(target=refine, name="refine-older-ahead", daemon=True).start()
        except BaseException:
            self._refine_lock.release()
            raise

    def _joint(self, views: list[ViewResult]) -> tuple[ViewRefinement, NDArray[np.float64], str]:
        """The joint refinement of ``views`` (:func:`refine_views`) with the prior it ran under (per view,
        column 0 mm, column 1 rad) and its source, kept as the one the refinement of these views and a newer
        one begins with (:attr:`_older`). Called under :attr:`_refine_lock`."""
        done = tuple(v.index for v in views)
        if self._older is not None and self._older[0] == done:
            return self._older[1], self._older[2], self._older[3]
        sigma, source = self._prior(views)
        found = refine_views([v.eval_W for v in views], sigma[:, 0], sigma[:, 1], **self.refine_inputs(views))
        self._older = (done, found, sigma, source)
        return found, sigma, source

    def refine_inputs(self, views: list[ViewResult]) -> dict[str, Any]:
        """What :func:`refine_views` and :func:`refine_newest` take of ``views`` besides their points and
        prior: their local planes, camera centres, KD-trees, indices (each pair's sample seed) and the job's
        overlap cache (the pairs' first matchings made as the views arrived)."""
        return {
            "planes": [v.planes for v in views],
            "cameras": [v.camera_W for v in views],
            "trees": [v.eval_tree if len(v.eval_W) else None for v in views],
            "ids": [v.index for v in views],
            "cache": self._overlaps,
        }

    def _prior(self, views: list[ViewResult]) -> tuple[NDArray[np.float64], str]:
        """The views' pose prior (:func:`view_pose_prior`, from their joints when all have them)."""
        joints = [np.asarray(v.summary["joints_rad"]) for v in views if "joints_rad" in v.summary]
        return view_pose_prior(self.cfg, joints if len(joints) == len(views) else None)

    def _refine(self, views: list[ViewResult]) -> tuple[list[int], ViewRefinement]:
        """The refinement of ``views`` (in index order; kept while they are the completed views): of three or
        more, the joint refinement of all but the newest (:meth:`_joint`, made ahead or now) and the newest
        view refined alone against them (:func:`refine_newest`); of fewer, or where the newest view's pairs
        would change which views are held, the joint refinement of all (docs/analysis.md, "Multi-view
        refinement"). Called under :attr:`_refine_lock`."""
        done = tuple(v.index for v in views)
        if self._refinement is None or self._refinement[0] != done:
            sigma, source = self._prior(views)
            found = None
            if len(views) >= 3:
                older, older_sigma, _ = self._joint(views[:-1])
                found = refine_newest(
                    older,
                    [v.eval_W for v in views],
                    float(sigma[-1, 0]),
                    float(sigma[-1, 1]),
                    **self.refine_inputs(views),
                )
                if found is not None:  # the others under their own joint solve's prior, the newest its own
                    sigma = np.vstack([older_sigma, sigma[-1:]])
            if found is None:
                found, sigma, source = self._joint(views)
            prior = {
                "prior": source,
                "prior_sigma_mm": np.round(sigma[:, 0], 4).tolist(),
                "prior_sigma_deg": np.round(np.rad2deg(sigma[:, 1]), 5).tolist(),
            }
            self._refinement = (done, found, prior)
            self._moved.clear()
        return list(self._refinement[0]), self._refinement[1]

    def _moved_eval(
        self, run: RunFolder, T_W_align: NDArray[np.float64] | None = None
    ) -> dict[int, NDArray[np.float64]]:
        """The completed views' evaluation points moved by their refinement (and then by ``T_W_align``, the
        alignment's correction in {W}, when given), by view index; kept while the refinement holds."""
        done, found = self.refinement(run)
        key = b"" if T_W_align is None else np.asarray(T_W_align, dtype=np.float64).tobytes()
        if key not in self._moved:
            self._moved[key] = {
                i: transform_points(T if T_W_align is None else T_W_align @ T, self.views.get(run, i).eval_W)
                for i, T in zip(done, found.T, strict=True)
            }
        return self._moved[key]

    def _measured(
        self, run: RunFolder, T_W_align: NDArray[np.float64] | None = None
    ) -> dict[int, MeasuredView]:
        """The measured views by view index (skipped or unmeasured views are absent), each moved by its
        refinement (and by ``T_W_align``, the alignment's correction in {W}, when given), with its deviations
        from the nominal measured there and the nominal's normal at each point (its closest triangle's)."""
        done, found = self.refinement(run)
        if not done:
            return {}
        moved = self._moved_eval(run, T_W_align)
        points = [moved[i] for i in done]
        error_map = signed_distance(self.nominal, np.vstack(points))  # one call: all cores
        # the nominal's normal at each point, its closest triangle's (the accuracy map's incidence check):
        # found with the deviation, not looked up again among the plan's surface samples
        normals = self.nominal.face_normals[error_map.face]
        ends = np.cumsum([len(p) for p in points])[:-1]
        out = {}
        for i, T_fix, dev, n in zip(
            done, found.T, np.split(error_map.deviation_mm, ends), np.split(normals, ends), strict=True
        ):
            view = self.views.get(run, i)
            T = T_fix if T_W_align is None else T_W_align @ T_fix
            out[i] = MeasuredView(
                T @ view.T_W_C,
                moved[i],
                view.regions,
                deviation_mm=dev,
                uncertainty_mm=view.eval_u,
                nominal_normals_W=n,
            )
        return out

    def _evaluation_alignment(self, run: RunFolder) -> tuple[NDArray[np.float64] | None, str]:
        """The recipe's alignment of what is measured so far, as a correction in {W} (None for kinematic
        alignment, or while the measurement does not allow it yet: a datum not seen). Coverage and holes are
        judged on the aligned points, so a part off its fixture shows no false holes."""
        if self.recipe.alignment.method == "kinematic":
            return None, "kinematic"
        moved = self._moved_eval(run)
        if not moved:
            return None, "no points yet"
        T_P_W = invert(self.T_W_P)
        points_P = transform_points(T_P_W, np.vstack(list(moved.values())))
        try:
            found = self.aligner.align(points_P)
        except AlignmentError as exc:
            return None, f"kinematic until the alignment can be made: {exc}"
        return self.T_W_P @ found.T @ T_P_W, self.recipe.alignment.method

    def _covered(self, run: RunFolder, T_W_align: NDArray[np.float64] | None) -> NDArray[np.bool_]:
        """Which of the plan's surface samples the completed views' evaluation points cover, the views moved
        by their refinement and then by ``T_W_align`` ({W}), counted in each view's own KD-tree."""
        done, found = self.refinement(run)
        A = np.eye(4) if T_W_align is None else T_W_align
        st, surface = self.plan_model.sensor.settings, self.plan_model.surface
        views = [(self.views.get(run, i).eval_tree, A @ T) for i, T in zip(done, found.T, strict=True)]
        return covered_by_views(surface, views, st.point_density_per_mm2, st.coverage_radius_mm)

    def _map_pairs(self, run: RunFolder, done: Sequence[int]) -> PairsOf:
        """The feedback maps' pairs (cell.planning.feedback.PairsOf) of the views ``done`` (view indices, by
        position in the maps' list): each view's evaluation points paired with their nearest in the other
        view at the two views' kinematic poses, found once per pair (as the later view arrives, by
        :meth:`_first_overlaps`, or when first asked after a resume: the same numbers). The maps compare the
        pairs at the refined (and aligned) poses. Pairing before the refinement instead of after it is a small
        model change: its corrections are tens of um against the 0.5 mm link distance, so only points near
        the link distance or between two near-equidistant neighbours pair differently (9 % of the demo
        pillar's pairs, the evaluation unchanged and the maps at tighter thresholds within 2 %;
        docs/benchmarks.md). It keeps the pairing off the evaluation after the last view."""

        def pairs(a: int, b: int, link_mm: float) -> tuple[NDArray[np.integer], NDArray[np.integer]]:
            va, vb = self.views.get(run, done[a]), self.views.get(run, done[b])
            tree = vb.eval_tree if len(vb.eval_W) else None
            return self._pairs.pairs(va.index, vb.index, link_mm, va.eval_W, tree)

        return pairs

    def _feedback_round(self, run: RunFolder) -> FeedbackRound:
        T_W_align, how = self._evaluation_alignment(run)
        measured = self._measured(run, T_W_align)
        fb = FeedbackPlanner(self.plan_model)
        covered = self._covered(run, T_W_align)
        u_max = self.u_target_mm / self.decision.k
        pairs = self._map_pairs(run, list(measured))
        ev = evaluate(fb, list(measured.values()), 1, np.zeros((0, 3)), u_max, covered=covered, pairs=pairs)
        # the moved points live on in ``measured`` as far as the replan needs them: not held beside the
        # registration or through the next views' scan (a hires run's 40 views: 0.1 GB a set)
        self._moved.clear()
        return FeedbackRound(fb, ev, measured, how)

    def evaluate(self, run: RunFolder, views: list[View], iteration: int) -> Evaluation:
        """Coverage, the accuracy map and Q of the views measured so far (the feedback round is kept in the
        result for :meth:`replan`). The newest view's maps' pairs (left by its decode: the plan's last view's)
        are found first, at the kinematic poses, while the refinement, made ahead, may still be running."""
        completed = self.views.completed(run)
        if completed:
            self._pair_maps(completed[-1], completed[:-1])
        loop = self._feedback_round(run)
        ev, measured = loop.evaluation, loop.measured
        _, found = self.refinement(run)
        figures = ev.to_json()
        del figures["qualified"], figures["Q"]
        figures |= {
            "views": len(views),
            "alignment": loop.alignment,
            "refinement": {
                "rms_before_mm": round(found.rms_before_mm, 4),
                "rms_after_mm": round(found.rms_after_mm, 4),
                "unregistered_views": [list(measured)[k] for k in found.unregistered if k < len(measured)],
            },
        }
        return Evaluation(ev.qualified, round(ev.q, 1), iteration, figures, state=loop)

    def evaluations_done(self) -> None:
        """No evaluation follows (the controller registers next): the caches the evaluations' refinement and
        maps kept are dropped, not held beside the registration (the hires pillar's 40 views: their pools,
        first matchings and maps' pairs with each other). Caches only: whatever asks for them again
        finds the same (cell.analysis.view_refinement.OverlapCache, cell.planning.feedback.PairCache)."""
        self._overlaps = OverlapCache()
        self._pairs = PairCache()

    def replan(self, run: RunFolder, views: list[View], evaluation: Evaluation) -> list[View]:
        """The feedback viewpoints g_k from the evaluation's round (computed again after a resume)."""
        # a merge made ahead of this round's last view is stale: more views come (not held through their scan)
        self.merge_bins_for(run).drop_ahead()
        loop = evaluation.state
        if not isinstance(loop, FeedbackRound):
            loop = self._feedback_round(run)
        fb, ev = loop.planner, loop.evaluation
        k = evaluation.iteration
        latest = [m for i, m in loop.measured.items() if (views[i].iteration or 0) == k]
        start = len(fb.log)
        proposed = fb.propose(k, latest, ev.covered, ev.ia, ev.iu)
        new = select_new(fb, proposed, [v.T_W_C for v in views if v.T_W_C is not None])
        if len(new) == 1:  # the views so far are all the refinement after it begins with (the decode of the
            # view before the last starts it when more are added)
            self._start_older_ahead(run, self.views.completed(run))
        for entry in fb.log[start:]:
            run.log(
                "decision", **{"kind": entry.get("event"), **{k: v for k, v in entry.items() if k != "event"}}
            )
        return [self._view(v, k + 1) for v in new]


def inspection_controller(
    devices: DeviceBundle,
    job: LambertianInspection,
    run: RunFolder,
    settings: ControllerSettings,
    on_progress: Any = None,
) -> Controller:
    """The controller for ``job`` on its cell: the robot config's limits and home, checked motion."""
    return Controller(
        devices,
        job,
        run,
        settings,
        robot_limits=RobotLimits.of(job.cfg.robot),
        home_joints_rad=np.deg2rad(job.cfg.robot.home_joints_deg),
        motion=job.motion_planner(settings.speed_fraction),
        on_progress=on_progress,
    )
