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
from cell.analysis.judge import judge
from cell.analysis.linkfilter import RIM_JUMP_MM, link_cluster, unreliable_pixels
from cell.analysis.merge import cut_unregistered, merge_views, voxel_subsample_index
from cell.analysis.regions import Coverage, Tolerance, region_from_config
from cell.analysis.report import write_report
from cell.analysis.report_files import (
    decode_uncertainty,
    encode_uncertainty,
    read_ply_field,
    read_ply_points,
    stored_points,
    write_file_set,
    write_ply,
)
from cell.analysis.uncertainty import TARGET_SHARE_OF_BAND, registered_cloud_uncertainty, view_uncertainty
from cell.analysis.view_refinement import LocalPlanes, ViewRefinement, estimate_normals, refine_views
from cell.calibration import (
    active_gamma_lut,
    active_hand_eye,
    active_sensor_config,
    active_triangulator,
    believed_flange,
    calibration_residual_px,
    calibration_source,
    pose_uncertainty_prior,
    view_pose_prior,
)
from cell.calibration.gamma import apply_lut
from cell.calibration_state import calibration_state
from cell.config import CellConfig, Recipe
from cell.contracts import CameraSettings, PixelFormat, TriggerMode
from cell.controller import Controller, ControllerSettings, RobotLimits
from cell.devices import DeviceBundle
from cell.errors import DeviceFault
from cell.geometry import invert, transform_points, transform_vectors
from cell.planning.coverage import coverage_fraction, covered_by_points
from cell.planning.feedback import Evaluation as FeedbackEvaluation
from cell.planning.feedback import FeedbackPlanner, evaluate, select_new
from cell.planning.kinematics import UR5E
from cell.planning.measured import DefectRegion, MeasuredView, measured_view_from_masks
from cell.planning.motion import MotionPlanner
from cell.planning.planner import Plan, plan_initial
from cell.planning.unseen import plan_feedback
from cell.planning.viewpoints import Viewpoint
from cell.raycast import RayCaster
from cell.run_data import Checkpoint, Evaluation, View
from cell.run_record import run_record
from cell.runs import RunFolder, write_json_atomic
from cell.sensing.decode import Reason, decode
from cell.sensing.patterns import PatternSet, measuring_patterns
from cell.sensing.scan import capture_stack
from cell.sensing.stack import check_stack
from cell.sensing.triangulate import normalized_coords
from cell.view_files import (
    load_eval_points,
    load_eval_uncertainty,
    load_view_points,
    save_raw_stack,
    save_view_points,
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


@dataclass
class Captured:
    """One view's pattern stack and where the robot was when it was grabbed (capture -> decode)."""

    images: list[NDArray[Any]]
    T_B_T: NDArray[np.float64]  # the flange pose the cell believes (cell.calibration.believed_flange)
    joints: NDArray[np.float64]
    camera: str


@dataclass
class FeedbackRound:
    """The feedback loop's evaluation with what it was computed from, kept for the replan that follows."""

    planner: FeedbackPlanner
    evaluation: FeedbackEvaluation
    measured: dict[int, MeasuredView]  # by view index
    alignment: str  # how the measured views were aligned for it


class LambertianInspection:
    """The job the controller runs for a recipe on a structured-light cell."""

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
        self.patterns: PatternSet = measuring_patterns(cfg.sensor.projector)
        lut = active_gamma_lut(cfg)  # the projector's measured response, linearised (cell calibrate gamma)
        if lut is not None:
            self.patterns = apply_lut(self.patterns, lut)
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
        self._refinement: tuple[tuple[int, ...], ViewRefinement, dict[str, Any]] | None = None
        self._planes: dict[int, LocalPlanes] = {}  # each view's local planes, kept between evaluations
        self.nominal = NominalMesh.from_trimesh(nominal_W)  # world frame, for cropping views to the part
        self._nominal_rays = RayCaster(nominal_W.vertices, nominal_W.faces, what="nominal mesh")

    # ------------------------------------------------------------------ planning
    @property
    def plan_model(self) -> Plan:
        """The f0 plan (recomputed deterministically after a resume: it also holds the surface samples)."""
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

    def capture(self, devices: DeviceBundle, view: View, index: int) -> Captured:
        devices.begin_view(index)
        self.prepare(devices)
        T_B_T = believed_flange(self.cfg, devices.robot)
        joints = np.asarray(devices.robot.joints(), dtype=np.float64)
        images = capture_stack(devices.camera, devices.projector, self.patterns)
        if not devices.projector.ready():  # a lamp that failed mid-stack leaves dark frames: measure again
            status = devices.projector.status()
            why = ", ".join(status.errors) or str(status)
            raise DeviceFault(devices.projector.name, f"not ready after the pattern stack: {why}")
        return Captured(images, T_B_T, joints, devices.camera.name)

    def decode(self, view: View, captured: Captured, out_dir: Path) -> dict[str, Any]:
        cam = self.cfg.sensor.camera
        stack = check_stack(
            captured.images,
            self.patterns,
            (cam.width_px, cam.height_px),
            cam.bit_depth,
            source=f"camera '{captured.camera}'",
        )
        decoded = decode(stack, self.patterns, cam.bit_depth)
        cloud = self.triangulator.triangulate(decoded)
        T_W_C = self.T_W_B @ captured.T_B_T @ self.T_T_C
        valid = cloud.valid
        kept = link_cluster(
            cloud.points_C, link_mm=self.settings.link_mm, min_cluster_px=self.settings.min_cluster_px
        )
        edges, oblique = unreliable_pixels(
            cloud.points_C,
            valid,
            self.projector_C,
            self.cfg.sensor.max_projector_incidence_deg,
            self.settings.edge_jump_mm,
        )
        # points lit too obliquely stay in the view for the refinement and the feedback loop (their tens of
        # um of bias matter less there than the constraints they add: without them the ideal world's
        # refinement slid a view by 0.85 mm) but not in the measured cloud (register)
        keep = valid & kept.keep & ~edges
        points_W = transform_points(T_W_C, cloud.points_C[keep])
        quality = cloud.contrast[keep].astype(np.float32)
        oblique_kept = oblique[keep]
        T_C_P, fx = self.sensor.projector.T_C_P.matrix(), self.sensor.camera.fx_px
        u = view_uncertainty(
            stack, self.patterns, decoded, cloud, T_C_P, fx, self.calibration_px, cam.bit_depth
        )
        deviation = signed_distance(self.nominal, points_W).deviation_mm
        crop = PartCrop(0.0, self.settings.table_margin_mm, self.settings.crop_mm).split(points_W, deviation)
        part = crop.part
        points_W, quality = points_W[part], quality[part]
        sub = voxel_subsample_index(points_W, self.settings.eval_voxel_mm)
        u_points = None if u is None else u.u_mm[keep][part]
        save_view_points(out_dir, points_W, quality, oblique_kept[part], sub, u_points)
        if self.cfg.retention.writes_raw_images:
            proj = self.cfg.sensor.projector
            save_raw_stack(out_dir, stack, self.patterns, cam.bit_depth, (proj.width_px, proj.height_px))
        cv2.imwrite(str(out_dir / "reasons.png"), cloud.reasons)
        regions = self._defects(T_W_C, cloud.reasons)
        _save_regions(out_dir / "defects.npz", regions)
        summary = {
            "T_W_C": T_W_C.tolist(),
            "T_B_T": captured.T_B_T.tolist(),
            "joints_rad": captured.joints.tolist(),
            "points": int(len(points_W)),
            "decoded": int(valid.sum()),
            "link_filtered": int((valid & ~kept.keep).sum()),
            "rim_filtered": int((valid & kept.keep & edges).sum()),
            "oblique_filtered": int(oblique_kept[part].sum()),
            "excluded": crop.counts(),
            "defects": {r: sum(d.reason == r for d in regions) for r in DEFECT_REASONS},
            "uncertainty": None if u is None else u.to_json(),
        }
        write_json_atomic(out_dir / "view.json", summary)
        return summary

    def _defects(self, T_W_C: NDArray[np.float64], reasons: NDArray[np.uint8]) -> list[DefectRegion]:
        """Hole regions per reason, located on the nominal surface by casting their pixels' rays on the
        CAD."""
        masks = {name: (reasons & np.uint8(bit)) > 0 for name, bit in DEFECT_REASONS.items()}
        holes = np.logical_or.reduce(list(masks.values()))
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
        their evaluation points, under the views' pose prior (:func:`view_pose_prior`: the kinematic
        calibration's, else the robot config's); recomputed when views were added (deterministic, so a resumed
        run gets the same)."""
        done = tuple(run.completed_views())
        if self._refinement is None or self._refinement[0] != done:
            points = [load_eval_points(run.view_dir(i)) for i in done]
            for i, p in zip(done, points, strict=True):
                if i not in self._planes:
                    self._planes[i] = estimate_normals(p)
            meta = [json.loads((run.view_dir(i) / "view.json").read_text()) for i in done]
            cameras = [np.asarray(m["T_W_C"])[:3, 3] for m in meta]
            joints = [np.asarray(m["joints_rad"]) for m in meta if "joints_rad" in m]
            sigma, source = view_pose_prior(self.cfg, joints if len(joints) == len(meta) else None)
            found = refine_views(
                points,
                sigma[:, 0],
                sigma[:, 1],
                seed=len(done),
                planes=[self._planes[i] for i in done],
                cameras=cameras,
            )
            prior = {
                "prior": source,
                "prior_sigma_mm": np.round(sigma[:, 0], 4).tolist(),
                "prior_sigma_deg": np.round(np.rad2deg(sigma[:, 1]), 5).tolist(),
            }
            self._refinement = (done, found, prior)
        return list(self._refinement[0]), self._refinement[1]

    def _measured(
        self, run: RunFolder, T_W_align: NDArray[np.float64] | None = None
    ) -> dict[int, MeasuredView]:
        """The measured views by view index (skipped or unmeasured views are absent), each moved by its
        refinement (and by ``T_W_align``, the alignment's correction in {W}, when given), with its deviations
        from the nominal measured there."""
        done, found = self.refinement(run)
        out = {}
        for i, T_fix in zip(done, found.T, strict=True):
            d = run.view_dir(i)
            meta = json.loads((d / "view.json").read_text())
            T = T_fix if T_W_align is None else T_W_align @ T_fix
            points = transform_points(T, load_eval_points(d))
            out[i] = MeasuredView(
                T @ np.asarray(meta["T_W_C"]),
                points,
                _load_regions(d / "defects.npz"),
                deviation_mm=signed_distance(self.nominal, points).deviation_mm,
                uncertainty_mm=load_eval_uncertainty(d),
            )
        return out

    def _evaluation_alignment(self, run: RunFolder) -> tuple[NDArray[np.float64] | None, str]:
        """The recipe's alignment of what is measured so far, as a correction in {W} (None for kinematic
        alignment, or while the measurement does not allow it yet: a datum not seen). Coverage and holes are
        judged on the aligned points, so a part off its fixture shows no false holes."""
        if self.recipe.alignment.method == "kinematic":
            return None, "kinematic"
        measured = self._measured(run)
        if not measured:
            return None, "no points yet"
        T_P_W = invert(self.T_W_P)
        points_P = transform_points(T_P_W, np.vstack([m.points_W for m in measured.values()]))
        try:
            found = self.aligner.align(points_P)
        except AlignmentError as exc:
            return None, f"kinematic until the alignment can be made: {exc}"
        return self.T_W_P @ found.T @ T_P_W, self.recipe.alignment.method

    def _feedback_round(self, run: RunFolder) -> FeedbackRound:
        T_W_align, how = self._evaluation_alignment(run)
        measured = self._measured(run, T_W_align)
        fb = FeedbackPlanner(self.plan_model)
        ev = evaluate(fb, list(measured.values()), 1, np.zeros((0, 3)), self.u_target_mm / self.decision.k)
        return FeedbackRound(fb, ev, measured, how)

    def evaluate(self, run: RunFolder, views: list[View], iteration: int) -> Evaluation:
        """Coverage, the accuracy map and Q of the views measured so far (the feedback round is kept in the
        result for :meth:`replan`)."""
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

    def replan(self, run: RunFolder, views: list[View], evaluation: Evaluation) -> list[View]:
        """The feedback viewpoints g_k from the evaluation's round (computed again after a resume)."""
        loop = evaluation.state
        if not isinstance(loop, FeedbackRound):
            loop = self._feedback_round(run)
        fb, ev = loop.planner, loop.evaluation
        k = evaluation.iteration
        latest = [m for i, m in loop.measured.items() if (views[i].iteration or 0) == k]
        start = len(fb.log)
        proposed = fb.propose(k, latest, ev.covered, ev.ia, ev.iu)
        new = select_new(fb, proposed, [v.T_W_C for v in views if v.T_W_C is not None])
        for entry in fb.log[start:]:
            run.log(
                "decision", **{"kind": entry.get("event"), **{k: v for k, v in entry.items() if k != "event"}}
            )
        return [self._view(v, k + 1) for v in new]

    # ------------------------------------------------------------------ results
    @property
    def aligner(self) -> Aligner:
        """The recipe's alignment against the nominal in the part frame (datums resolved on first use)."""
        if self._aligner is None:
            nominal_P = self.nominal_W.copy().apply_transform(invert(self.T_W_P))
            self._aligner = Aligner(self.recipe.alignment, nominal_P)
        return self._aligner

    def register(self, run: RunFolder, views: list[View]) -> dict[str, Any]:
        """All views into the part frame via the kinematic chain (eqs 4.1-4.4: T_P_W @ p_W, the view points
        already being in {W} through robot pose and hand-eye), refined against each other, merged on a voxel
        grid weighted by quality (a view the refinement could not register gives only the surface no
        registered view measured: :func:`cut_unregistered`), then moved by the recipe's alignment
        (cell.analysis.alignment). An alignment the measurement does
        not allow leaves the kinematic cloud and makes the verdict incomplete (``alignment.error``)."""
        T_P_W = invert(self.T_W_P)
        done, refined = self.refinement(run)
        points, weights, u_decode = [], [], []
        for i, T_fix in zip(done, refined.T, strict=True):
            view = load_view_points(run.view_dir(i))
            measured = ~view.oblique  # the sensor's points, without those lit too obliquely
            points.append(transform_points(T_P_W @ T_fix, view.points_W[measured]))
            weights.append(np.square(view.quality[measured]).astype(np.float64) + 1e-6)
            u = view.uncertainty  # None in run folders from before issue 17
            u_decode.append(np.full(len(points[-1]), np.nan) if u is None else u[measured].astype(np.float64))
        if not points or not sum(len(p) for p in points):
            return {"n_points": 0, "views": len(points)}
        eval_points = [load_eval_points(run.view_dir(i)) for i in done]
        refinement = {
            **refined.to_json(eval_points),
            "unregistered_views": [done[k] for k in refined.unregistered],
            **(self._refinement[2] if self._refinement else {}),  # the prior it was found under
        }
        n_points_views = int(sum(len(p) for p in points))
        refinement["unregistered_points_dropped"] = cut_unregistered(
            points, weights, refined.unregistered, self.recipe.plan.coverage_radius_mm, u_decode
        )
        merged = merge_views(points, weights, voxel_mm=self.settings.merge_voxel_mm)
        method = self.recipe.alignment.method
        try:
            found = self.aligner.align(merged.points_mm)
            points_P = transform_points(found.T, merged.points_mm)
            alignment = found.to_json()
        except AlignmentError as exc:
            points_P, alignment = merged.points_mm, {"method": method, "error": str(exc)}
        prior = pose_uncertainty_prior(self.cfg, self._refinement[2] if self._refinement else {})
        unc = registered_cloud_uncertainty(
            merged,
            weights,
            u_decode,
            refined,
            prior,
            self.nominal,
            self.T_W_P,
            alignment,
            self.aligner.datums,
        )
        u_ply = {"uncertainty": encode_uncertainty(unc.u_mm)}
        write_file_set(run.results_dir, {"cloud.ply": lambda path: write_ply(path, points_P, fields=u_ply)})
        return {
            "n_points": int(len(points_P)),
            "n_points_views": n_points_views,
            "views": len(points),
            "merge_voxel_mm": self.settings.merge_voxel_mm,
            "method": "kinematic chain (robot pose, hand-eye, part placement); views refined against each "
            f"other; weighted voxel merge; alignment: {method}",
            "refinement": refinement,
            "alignment": alignment,
            "uncertainty": {
                **unc.budget(),
                "calibration": self.calibration_residual,
                "poses": prior.get("prior"),
            },
        }

    def inspectable_coverage(self, run: RunFolder, T_P_cloud: NDArray[np.float64] | None = None) -> Coverage:
        """Coverage of the inspectable nominal surface (what the planner can see: not the underside on the
        table) at the recipe's point density, from the measured views moved by the alignment ``T_P_cloud``."""
        plan, st = self.plan_model, self.recipe.plan
        s = plan.surface
        measured = self._measured(run)
        pts = np.vstack([m.points_W for m in measured.values()]) if measured else np.zeros((0, 3))
        if T_P_cloud is not None:
            pts = transform_points(self.T_W_P @ T_P_cloud @ invert(self.T_W_P), pts)
        covered = covered_by_points(s, pts, st.point_density_per_mm2, st.coverage_radius_mm)
        ins = s.inspectable
        return Coverage(
            fraction=coverage_fraction(s, covered),
            area_mm2=float(s.inspectable_area_mm2),
            radius_mm=st.coverage_radius_mm,
            min_count=1,
            density_per_mm2=st.point_density_per_mm2,
            samples_mm=transform_points(invert(self.T_W_P), s.points[ins]),
            sample_face=s.face[ins],
            covered=covered[ins],
        )

    def report(self, run: RunFolder, registration: dict[str, Any], csv: bool = False) -> dict[str, Any]:
        """Judge the registered cloud (results/cloud.ply as :meth:`register` wrote it, or as an earlier
        report rewrote it: the same points in the same order) and write the report into results/, with
        deviations.csv when ``csv``. The report replaces the cloud.ply by one with the deviation field."""
        legacy = run.results_dir / "points_P.npy"  # a run registered before the cloud was stored once
        pts_P = np.load(legacy) if legacy.is_file() else read_ply_points(run.results_dir / "cloud.ply")
        u_stored = None if legacy.is_file() else read_ply_field(run.results_dir / "cloud.ply", "uncertainty")
        u = None if u_stored is None else decode_uncertainty(u_stored)
        # as cloud.ply stores them (float32): a no-op on a cloud written so; an older float64 cloud is judged
        # as the report will store it, so the next rebuild gives the same figures
        pts_P = stored_points(pts_P)
        nominal_P = self.nominal_W.copy().apply_transform(invert(self.T_W_P))
        tol = self.recipe.tolerance
        checkpoint = Checkpoint.from_json(run.load_checkpoint())
        evaluation = checkpoint.evaluation.to_json() if checkpoint.evaluation is not None else {}
        excluded = {
            "unregistered_view_measured_elsewhere_points": int(
                registration.get("refinement", {}).get("unregistered_points_dropped", 0)
            )
        }
        for i in run.completed_views():
            for reason, n in (
                json.loads((run.view_dir(i) / "view.json").read_text()).get("excluded", {}).items()
            ):
                excluded[f"{reason}_points"] = excluded.get(f"{reason}_points", 0) + int(n)
        alignment = registration.get("alignment") or {"method": "kinematic"}
        T_align = np.asarray(alignment["T_P_cloud"]) if "T_P_cloud" in alignment else None
        calibration = calibration_state(self.cfg, self.recipe.requires_calibration)
        reasons = list(calibration["incomplete_reasons"])
        if "error" in alignment:
            reasons.append(f"alignment ({alignment['method']}) failed: {alignment['error']}")
        if evaluation.get("v_mm2", 0.0) > evaluation.get("setpoint", float("inf")):
            reasons.append(
                f"overlapping views disagree by more than {self.recipe.plan.accuracy_tol_mm} mm over "
                f"{evaluation['v_mm2']:.0f} mm^2 after refinement, more than the set point of Q allows "
                f"({evaluation['setpoint']:.0f} mm^2): the calibration does not hold (cell calibrate all)"
            )
        decision = self.decision
        if u is None or not np.isfinite(u).any():
            u = None
            if decision.rule == "guarded":  # a run registered before points carried their uncertainty
                reasons.append("the guarded decision rule needs the points' uncertainty; this run has none")
                decision = DecisionRule()
        plan = plan_feedback(self.plan_model, self.recipe)  # what no reachable viewpoint sees, for the reader
        inp = judge(
            NominalMesh.from_trimesh(nominal_P),
            pts_P,
            Tolerance(tol.lower, tol.upper),
            n_points_input=int(registration.get("n_points_views", len(pts_P))),
            regions=[region_from_config(spec) for spec in self.recipe.regions],
            min_defect_points=self.settings.min_defect_points,
            excluded=excluded,
            coverage=self.inspectable_coverage(run, T_align),
            min_coverage=self.recipe.min_coverage,
            warnings=[*alignment.get("warnings", []), *plan.warnings],
            incomplete_reasons=reasons,
            alignment=alignment,
            calibration=calibration,
            uncertainty_mm=u,
            decision=decision,
            uncertainty=registration.get("uncertainty"),
            metadata={
                "part": self.part_name,
                "cad": Path(self.recipe.part.cad).name,
                "views": [
                    {"patch": v.patch, "source": v.source, "iteration": v.iteration} for v in checkpoint.views
                ],
                "registration": registration,
                "evaluation": evaluation,
                "plan": plan.to_json(),  # predicted coverage, min_coverage, unseen_surfaces, warnings
                "geometry_source": self.geometry_source,
                "run": run_record(run, self.cfg.name),
            },
        )
        doc = write_report(run.results_dir, inp, pictures=self.settings.pictures, csv=csv)
        legacy.unlink(missing_ok=True)  # cloud.ply now holds its points as judged (float32)
        return {
            "verdict": doc.get("verdict"),
            "n_points": doc.get("n_points"),
            "coverage": doc.get("coverage"),
            "deviation": doc.get("deviation"),
        }


def _save_regions(path: Path, regions: list[DefectRegion]) -> None:
    arrays: dict[str, Any] = {
        "reasons": np.array([r.reason for r in regions], dtype="U16"),
        "pixels": np.array([r.pixels for r in regions], dtype=np.int64),
    }
    for k, r in enumerate(regions):
        arrays[f"boundary_{k}"] = r.boundary_W
        arrays[f"points_{k}"] = r.points_W
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def _load_regions(path: Path) -> list[DefectRegion]:
    with np.load(path) as data:
        return [
            DefectRegion(str(reason), data[f"boundary_{k}"], data[f"points_{k}"], int(px))
            for k, (reason, px) in enumerate(zip(data["reasons"], data["pixels"]))
        ]


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
