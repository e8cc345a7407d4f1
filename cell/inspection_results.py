"""The inspection's results, after its views are measured: the registered cloud (all views in the part frame,
refined against each other, merged, aligned) with its error map and coverage, judged into the verdict, which
is published first (report.json), and the rest of the report after it (cloud.ply, report.html).

A part of :class:`cell.inspection.LambertianInspection` (its base class): the controller calls ``register``
(in its worker, beside ``evaluate``), ``report`` and ``render``; ``cell report`` calls the last two again.
"""

from __future__ import annotations

import copy
import json
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.analysis.alignment import Aligner, AlignmentError
from cell.analysis.decision import DecisionRule
from cell.analysis.errormap import ErrorMap, NominalMesh, signed_distance
from cell.analysis.judge import judge
from cell.analysis.merge import (
    HeldCut,
    MergedCloud,
    PartialMerge,
    ViewBins,
    bin_view,
    held_redundant,
    load_kernels,
    merge_bins,
    merge_bins_ahead,
)
from cell.analysis.regions import Coverage, Tolerance, region_from_config
from cell.analysis.report import ReportInput, default_link_radius, write_page, write_verdict
from cell.analysis.report_files import decode_uncertainty, read_ply_field, read_ply_points, stored_points
from cell.analysis.table_seam import table_seam
from cell.analysis.uncertainty import MergeShares, registered_cloud_uncertainty
from cell.calibration import pose_uncertainty_prior
from cell.calibration_state import calibration_state
from cell.config import CellConfig, Recipe
from cell.errors import CalledOff, ConfigError
from cell.geometry import invert, transform_points, transform_vectors
from cell.inspection_views import ViewResult, ViewStore
from cell.planning.coverage import coverage_fraction, covered_by_views
from cell.planning.unseen import plan_feedback
from cell.run_data import Checkpoint, View
from cell.run_record import run_record
from cell.runs import RunFolder

if TYPE_CHECKING:
    from cell.analysis.view_refinement import ViewRefinement
    from cell.inspection import InspectionSettings
    from cell.planning.planner import Plan

# the views' merge bins (cell.analysis.merge.ViewBins, 40 bytes an occupied voxel of a view) kept in memory at
# most, the newest first: a 1024x768 camera's dozen pillar views (7-23 MB each, 152 MB) stay; of a 5 MP
# camera's 40 (15-22 MB each) the first ones made are dropped and binned again from their points when merged
MERGE_BINS_KEPT_BYTES = 160_000_000
# views of more measured points than this are not binned as they arrive but when first merged (as a resumed
# run's): a 1024x768 camera's views (at most 0.79M pixels) are, a 5 MP camera's (1.7M points a pillar view)
# are not, whose bins would hold up to the budget above through the scan, where its peak memory was
# (docs/benchmarks.md, item 5); the merge is the same either way (tests/test_inspect_e2e.py)
ARRIVAL_BINNING_MAX_POINTS = 1_000_000
# a merge made ahead of the last view (:class:`MergeAhead`) holds up to about this many bytes a bin of the
# views it merged (48 a voxel, 20 a view's voxel, 48 a brick of voxels: 48 on the demo pillar, 181 MB for its
# first 11 views' 3.79M bins, 0.56 voxels a bin), and is not made beyond MERGE_AHEAD_MAX_BYTES: it is held
# while the last view is measured and decoded (1024x768 views only: ARRIVAL_BINNING_MAX_POINTS)
MERGE_AHEAD_BYTES_A_BIN = 60
MERGE_AHEAD_MAX_BYTES = 400_000_000


class MergeBins:
    """The views' bins for the registration's merge (:func:`cell.analysis.merge.bin_view`: at their kinematic
    positions in {P}), made once a view, as it arrives (the decode worker) or when first merged (a resumed
    run's views), and their measured points' counts. The bins depend on the view alone and the merge only on
    the bins, so a resumed run merges what an uninterrupted one does. Thread-safe: the bins and the counts
    are written and read under one lock (a merge holds it throughout: a view binned meanwhile waits)."""

    def __init__(self, voxel_mm: float, run: Path, kept_bytes: int = MERGE_BINS_KEPT_BYTES) -> None:
        self.run = run  # the run folder whose views these are
        self.voxel_mm = voxel_mm
        self.kept_bytes = kept_bytes
        self.n_points: dict[int, int] = {}  # by view index: its measured points (not the oblique ones)
        self._bins: dict[int, ViewBins] = {}  # by view index, the first ones dropped beyond ``kept_bytes``
        self._merging: set[int] = set()  # views binned when merged (not as they arrived): kept for it only
        self._lock = threading.RLock()  # reentrant: a merge asks for views, which may be binned then
        self._ahead: MergeAhead | None = None  # the merge of all views but the last, made ahead
        self._forgotten: dict[int, int] = {}  # by view index: times forgotten (voids a merge made ahead)

    def add(self, index: int, bins: ViewBins, n_points: int) -> None:
        """Keep view ``index``'s ``bins`` (within the budget: the newest stay) and its points' count."""
        with self._lock:
            self.n_points[index] = n_points
            self._bins.pop(index, None)
            self._bins[index] = bins
            held = sum(b.nbytes for b in self._bins.values())
            for k in list(self._bins):
                if held <= self.kept_bytes or k == index:
                    break
                held -= self._bins.pop(k).nbytes

    def view(self, index: int, make: Callable[[], tuple[ViewBins, int]]) -> ViewBins:
        """View ``index``'s bins: kept, else made by ``make`` (its bins and points' count: binned again from
        its points) and kept until the merge's end (:meth:`merge`)."""
        with self._lock:
            bins = self._bins.get(index)
            if bins is not None:
                return bins
            bins, n = make()
            self.add(index, bins, n)  # within the budget, for the merge's second pass
            self._merging.add(index)
            return bins

    def merge(
        self,
        views: Callable[[int], ViewBins],
        keep: Sequence[NDArray[np.bool_] | None],
        T: Sequence[NDArray[np.float64]],
        each_view: MergeShares,
        ahead: PartialMerge | None = None,
    ) -> MergedCloud | None:
        """:func:`cell.analysis.merge.merge_bins` of these bins, under the lock; with ``ahead``, the merge
        of all views but the last made ahead with the same ``keep`` and ``T`` (:class:`MergeAhead`), only the
        last view's share (:meth:`cell.analysis.merge.PartialMerge.finish`: the same merge to the bit). The
        bins of views binned when merged (a 5 MP camera's, a resumed run's) are dropped after it: kept, they
        were held through the next views' scan or beside the rest of the registration (160 MB; issue 16,
        item 5), and a merge again makes the same."""
        with self._lock:
            try:
                if ahead is not None:
                    last = len(T) - 1
                    return ahead.finish(views(last), keep[last], T[last], each_view)
                return merge_bins(self.voxel_mm, views, keep, T, each_view)
            finally:  # also when the merge stops midway (a registration called off)
                for index in self._merging:
                    self._bins.pop(index, None)
                self._merging.clear()

    def has(self, index: int) -> bool:
        """Whether view ``index`` was binned (its bins may have been dropped since, beyond the budget)."""
        with self._lock:
            return index in self.n_points

    def points(self, indices: Sequence[int]) -> int:
        """The measured points of the views ``indices`` (all binned)."""
        with self._lock:
            return int(sum(self.n_points[i] for i in indices))

    def forget(self, index: int) -> None:
        """Drop view ``index``'s bins and count (it is measured again: binned anew when merged), and a merge
        made ahead of it (:class:`MergeAhead`; one being made now is not kept). A merge made ahead of other
        views stays (the plan's last view, forgotten as its decode begins, is not in it)."""
        with self._lock:
            self._bins.pop(index, None)
            self.n_points.pop(index, None)
            self._merging.discard(index)
            if self._ahead is not None and index in self._ahead.indices:
                self._ahead = None
            self._forgotten[index] = self._forgotten.get(index, 0) + 1

    def bins_ahead(self, indices: Sequence[int]) -> tuple[list[ViewBins], tuple[int, ...]] | None:
        """The kept bins of the views ``indices`` and how often each was forgotten so far (for
        :meth:`keep_ahead`), or None when a view's are not kept (dropped beyond the budget, or not binned as
        it arrived: a view of more than :data:`ARRIVAL_BINNING_MAX_POINTS`, a 5 MP camera's): no merge is
        made ahead of them."""
        with self._lock:
            bins = [self._bins.get(i) for i in indices]
            big = any(self.n_points.get(i, 0) > ARRIVAL_BINNING_MAX_POINTS for i in indices)
            if big or any(b is None for b in bins):
                return None
            return [b for b in bins if b is not None], self._times_forgotten(indices)

    def _times_forgotten(self, indices: Sequence[int]) -> tuple[int, ...]:
        return tuple(self._forgotten.get(i, 0) for i in indices)

    def keep_ahead(self, ahead: MergeAhead, forgotten: tuple[int, ...]) -> bool:
        """Keep ``ahead`` for the registration (in place of one kept before) unless one of its views was
        forgotten since its bins were taken (``forgotten``: :meth:`bins_ahead`'s). Whether it was kept."""
        with self._lock:
            if forgotten != self._times_forgotten(ahead.indices):
                return False
            self._ahead = ahead
            return True

    def take_ahead(self) -> MergeAhead | None:
        """The merge made ahead, no longer kept here (a registration uses it once, or finds it stale)."""
        with self._lock:
            ahead, self._ahead = self._ahead, None
            return ahead

    def drop_ahead(self) -> None:
        """Drop the merge made ahead (more views are planned: it is stale; the job's replan)."""
        self.take_ahead()


@dataclass
class MergeAhead:
    """The registration's held-view cut and merge of all views but the last (:meth:`InspectionResults.
    merge_ahead`), for the views ``indices`` (in their order) refined by ``T`` ({P} to {P}), ``unregistered``
    of them (their positions) cut by ``held`` to the masks ``keep``: what the registration after the last
    view uses when its refinement gives these views the same corrections and which are unregistered, bit
    for bit (:meth:`fits`), and the cut the same masks (:meth:`keeps`)."""

    indices: tuple[int, ...]
    T: list[NDArray[np.float64]]
    unregistered: tuple[int, ...]
    held: HeldCut
    keep: list[NDArray[np.bool_] | None]
    counts: dict[int, NDArray[np.int32]]  # the held views' points per bin (for the count of points cut)
    merge: PartialMerge

    @property
    def nbytes(self) -> int:
        """The bytes it holds (besides the views' bins)."""
        return self.merge.nbytes + self.held.nbytes + sum(k.nbytes for k in self.keep if k is not None)

    def fits(
        self, done: Sequence[int], T: Sequence[NDArray[np.float64]], unregistered: Sequence[int]
    ) -> bool:
        """Whether the views ``done`` (indices, in order) refined by ``T`` with ``unregistered`` (positions)
        are these views and one after them, these refined and unregistered as here, to the bit."""
        n = len(self.indices)
        return (
            len(done) == n + 1
            and tuple(done[:n]) == self.indices
            and (not n or done[n] > self.indices[-1])
            and len(T) == n + 1
            and all(np.asarray(a, np.float64).tobytes() == b.tobytes() for a, b in zip(T, self.T))
            and tuple(sorted(k for k in set(unregistered) if k < n)) == self.unregistered
        )

    def keeps(self, keep: Sequence[NDArray[np.bool_] | None]) -> bool:
        """Whether these views' masks in ``keep`` (all views') are those the merge was made with."""
        return all(
            (a is None and b is None) or (a is not None and b is not None and a.tobytes() == b.tobytes())
            for a, b in zip(keep, self.keep, strict=False)
        )


@dataclass
class RegisteredCloud:
    """The registered cloud in {P} (mm) and what judging it needs that the evaluation does not change: its
    signed deviations from the nominal and the coverage at its alignment (None: computed when judged), and
    the cloud judged (None: judged when reported, e.g. a cloud read from cloud.ply)."""

    registration: dict[str, Any]
    points_P: NDArray[np.float64]
    error_map: ErrorMap | None = None
    coverage: Coverage | None = None
    uncertainty_mm: NDArray[np.float64] | None = None  # each point's u (None: a run from before issue 17)
    # the cloud judged without the run's context (InspectionResults._judge; None: judged when reported)
    judged: ReportInput | None = None


class InspectionResults:
    """Registration, judging and the report of a :class:`cell.inspection.LambertianInspection` (which sets
    these attributes and provides the plan and the views' refinement)."""

    recipe: Recipe
    cfg: CellConfig
    nominal_W: trimesh.Trimesh
    T_W_P: NDArray[np.float64]
    settings: InspectionSettings
    part_name: str
    geometry_source: str
    nominal: NominalMesh  # {W}
    decision: DecisionRule
    calibration_residual: str
    views: ViewStore
    _lock: threading.RLock
    _aligner: Aligner | None
    _nominal_P: NominalMesh | None
    _cloud: RegisteredCloud | None
    _judged: tuple[ReportInput, dict[str, Any], bool] | None
    _refinement: tuple[tuple[int, ...], ViewRefinement, dict[str, Any]] | None
    _merge_bins: MergeBins | None  # the views' merge bins, made as they arrive (:meth:`bin_arrived_view`)
    _merge_bins_lock: threading.Lock

    if TYPE_CHECKING:

        @property
        def plan_model(self) -> Plan: ...

        def refinement(self, run: RunFolder) -> tuple[list[int], ViewRefinement]: ...

    @property
    def aligner(self) -> Aligner:
        """The recipe's alignment against the nominal in the part frame (datums resolved on first use)."""
        with self._lock:
            if self._aligner is None:
                nominal_P = self.nominal_W.copy().apply_transform(invert(self.T_W_P))
                self._aligner = Aligner(self.recipe.alignment, nominal_P)
            return self._aligner

    def merge_bins_for(self, run: RunFolder) -> MergeBins:
        """The views' merge bins of ``run`` (a job works on one run: another run's are forgotten)."""
        with self._merge_bins_lock:
            state = self._merge_bins
            if state is None or state.run != run.path:
                state = MergeBins(self.settings.merge_voxel_mm, run.path)
                self._merge_bins = state
            return state

    def bin_arrived_view(self, run: RunFolder, view: ViewResult) -> None:
        """Bin a completed view for the registration's merge (:class:`MergeBins`), in the decode worker while
        the robot moves on: what the merge after the last view would otherwise begin with. A view of more than
        :data:`ARRIVAL_BINNING_MAX_POINTS` is left to the merge. The merge's compiled kernels are loaded
        here too, once a process."""
        load_kernels()
        if int(view.summary["points"]) > ARRIVAL_BINNING_MAX_POINTS:
            return
        self.merge_bins_for(run).add(view.index, *self._view_bins(view))

    def merge_ahead(
        self,
        run: RunFolder,
        done: Sequence[int],
        T: Sequence[NDArray[np.float64]],
        unregistered: Sequence[int],
    ) -> bool:
        """Make the registration's held-view cut and merge of the views ``done`` (indices, ascending; all
        of the run's completed views but the plan's last, which comes after them) ahead of the last view,
        from their refinement: ``T`` (:attr:`cell.analysis.view_refinement.ViewRefinement.T` of these views,
        {W} to {W}) and ``unregistered`` (positions in ``done``). For the refinement made ahead (issue 16,
        item 2), which refines these views jointly while the robot moves to and measures the last one and
        after it refines the last view alone, keeping these corrections exactly: :meth:`register` then does
        only the last view's share of the cut and the merge (:class:`cell.analysis.merge.HeldCut`,
        :class:`cell.analysis.merge.PartialMerge`), the same results to the bit, when its refinement gives
        these views the same ``T`` to the bit and the same unregistered ones and the last view cuts no held
        one further (:meth:`MergeAhead.fits`, :meth:`MergeAhead.keeps`); else it merges in full as without
        it. Call it before the refinement made ahead is handed over (the registration waits for that and
        takes what is kept then; after the earlier views' bins are made, :meth:`bin_arrived_view`). Kept in
        the run's :class:`MergeBins` until the registration takes it, one of these views is forgotten
        (measured again; the last view's decode forgets the last view, which leaves it) or
        :meth:`MergeBins.drop_ahead`; not made (False) when a view's bins are not kept
        (a 5 MP camera's views, over :data:`ARRIVAL_BINNING_MAX_POINTS`, are not binned as they arrive), it
        would hold more than :data:`MERGE_AHEAD_MAX_BYTES`, or the merge fails (the registration's says
        why). Whether it was made and kept."""
        state = self.merge_bins_for(run)
        got = state.bins_ahead(done)
        if got is None or len(T) != len(done):
            return False
        bins, forgotten = got
        if MERGE_AHEAD_BYTES_A_BIN * sum(len(b) for b in bins) > MERGE_AHEAD_MAX_BYTES:
            return False
        T_P_W = invert(self.T_W_P)
        T_P = [T_P_W @ T_k @ self.T_W_P for T_k in T]  # as the registration has them
        try:
            held = HeldCut(lambda k: bins[k], T_P, unregistered, self.recipe.plan.coverage_radius_mm)
            keep = [None if (cut := held.redundant.get(k)) is None else ~cut for k in range(len(bins))]
            partial = merge_bins_ahead(self.settings.merge_voxel_mm, lambda k: bins[k], keep, T_P)
        except ConfigError:  # what the registration's full merge says again (a view beyond the key's range)
            return False
        counts = {k: bins[k].count for k in held.held}
        ahead = MergeAhead(tuple(done), T_P, tuple(held.held), held, keep, counts, partial)
        return state.keep_ahead(ahead, forgotten)

    def _view_bins(self, view: ViewResult) -> tuple[ViewBins, int]:
        """A view's merge bins and its measured points' count: the sensor's points in {P}
        at their kinematic pose (T_P_W @ p_W), without those lit too obliquely, weighted by quality^2, with
        their decode u (NaN in run folders from before issue 17)."""
        held = view.points()
        keep = ~held.oblique
        points = transform_points(invert(self.T_W_P), held.points_W[keep])
        weights = np.square(held.quality[keep]).astype(np.float64) + 1e-6
        u = None if held.uncertainty is None else held.uncertainty[keep].astype(np.float64)
        return bin_view(points, weights, u, self.settings.merge_voxel_mm), len(points)

    def register(
        self, run: RunFolder, views: list[View], stop: threading.Event | None = None
    ) -> dict[str, Any]:
        """All views into the part frame via the kinematic chain (eqs 4.1-4.4: T_P_W @ p_W, the view points
        already being in {W} through robot pose and hand-eye), refined against each other, merged on a voxel
        grid weighted by quality (cell.analysis.merge: each view binned once at its kinematic positions, as it
        arrives; here each bin's mean is moved by its view's refinement and merged where it then falls; a
        view the refinement could not register gives only the surface no registered view measured:
        :func:`held_redundant`; the cut and merge of all views but the last made ahead, :meth:`merge_ahead`,
        are finished with the last view when the refinement fits them bit for bit), then moved by the recipe's
        alignment (cell.analysis.alignment). An alignment the measurement does not allow leaves the
        kinematic cloud and makes the verdict incomplete (``alignment.error``). The registered cloud stays in
        memory for :meth:`report` with its error map and coverage, computed here, and judged (:meth:`_judge`:
        the controller registers while it evaluates, so they are ready when the evaluation is and the
        verdict adds only the run's context); it is stored as results/cloud.ply with the report's page, and
        a resumed run registers again, deterministically, to the same points. ``stop`` (set by the
        controller when the evaluation beside it asks for more views, or the run pauses): :class:`CalledOff`
        at the next step (after the refinement, before each view's bins, after the merge and the points' u),
        keeping nothing."""

        def unless_called_off() -> None:
            if stop is not None and stop.is_set():
                raise CalledOff("registration called off: more views are coming")

        T_P_W = invert(self.T_W_P)
        state = self.merge_bins_for(run)
        # the newest view (the plan's last, which its decode left unbinned) is binned first, while the
        # refinement, made ahead (cell.inspection), may still be running
        for newest in self.views.completed(run)[-1:]:
            if not state.has(newest.index):
                self.bin_arrived_view(run, newest)
        done, refined = self.refinement(run)
        ahead = state.take_ahead()  # the cut and merge of all views but the last made ahead (merge_ahead)
        unless_called_off()
        stored = [self.views.get(run, i) for i in done]
        T_P = [T_P_W @ T @ self.T_W_P for T in refined.T]  # the views' refinement in {P}
        made_ahead = None if ahead is None else len(ahead.indices)
        if ahead is not None and not ahead.fits(done, T_P, refined.unregistered):
            run.log("merge_ahead", views=made_ahead, used=False, why="the earlier views' corrections changed")
            ahead = None

        def view(k: int) -> ViewBins:
            """View k's bins: kept, else binned again from its points (from its folder when the view store no
            longer holds them); asked for view by view, so a registration called off stops between views
            (a 5 MP view read from its folder and binned takes ~0.5 s)."""
            unless_called_off()
            return state.view(done[k], lambda: self._view_bins(stored[k]))

        # a held view's voxels near a registered view's (or an earlier held view's kept ones) are cut
        counts: dict[int, NDArray[np.int32]] = {}  # the held views' points per bin, for the count cut

        def held_bins(k: int) -> ViewBins:
            bins = view(k)
            if k in refined.unregistered:
                counts[k] = bins.count
            return bins

        if ahead is None:
            radius = self.recipe.plan.coverage_radius_mm
            redundant = held_redundant(held_bins, T_P, refined.unregistered, radius)
        else:  # the last view's share of the cut
            redundant = ahead.held.with_last(held_bins, T_P, refined.unregistered)
            for k, c in ahead.counts.items():
                counts.setdefault(k, c)
        unless_called_off()
        keep = [None if (cut := redundant.get(k)) is None else ~cut for k in range(len(stored))]
        partial = ahead.merge if ahead is not None and ahead.keeps(keep) else None
        if ahead is not None:  # which path the merge took, for the record (the same results either way)
            why = None if partial is not None else "the last view cut a held view further"
            run.log("merge_ahead", views=made_ahead, used=partial is not None, why=why)
        del ahead
        shares = MergeShares(len(stored))
        # numpy, scipy's trees and the kernels release the GIL: two threads for what follows, each step
        # writing its own results (those of one thread); the refinement's record beside the merge
        pool = ThreadPoolExecutor(2, thread_name_prefix="register")
        try:
            record = pool.submit(refined.to_json, [v.eval_W for v in stored])
            merged = state.merge(view, keep, T_P, shares, partial)
            del partial
            unless_called_off()
            n_points_views = state.points(done)
            if merged is None and not n_points_views:
                return {"n_points": 0, "views": len(stored)}
            if merged is None:
                raise ConfigError("registration merge: no finite points with a positive weight in any view")
            refinement = {
                **record.result(),
                "unregistered_views": [done[k] for k in refined.unregistered],
                **(self._refinement[2] if self._refinement else {}),  # the prior it was found under
            }
            refinement["unregistered_points_dropped"] = int(
                sum(int(counts[k][cut].sum()) for k, cut in redundant.items())
            )
            merging = {
                "n_points_views": n_points_views,
                "views": len(stored),
                "merge_voxel_mm": self.settings.merge_voxel_mm,
                "method": "kinematic chain (robot pose, hand-eye, part placement); views refined against "
                f"each other; weighted voxel merge; alignment: {self.recipe.alignment.method}",
                "refinement": refinement,
            }
            cloud, link_radius_mm = self._aligned_cloud(run, merged, shares, refined, merging, pool)
            del merged, shares  # before the judge's arrays are made
            unless_called_off()
            cloud.judged = self._judge(run, cloud, link_radius_mm, pool)
        finally:
            pool.shutdown()
            state.drop_ahead()  # (one made meanwhile is of these views: stale from here on)
        self._cloud = cloud
        return cloud.registration

    def _aligned(
        self, points_mm: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], dict[str, Any], NDArray[np.int64] | None]:
        """The merged cloud ``points_mm`` ({P} by the kinematic chain) moved by the recipe's alignment and
        rounded as cloud.ply stores them (float32, so a rebuilt report gives the same figures), the
        alignment's record (``error``: the measurement does not allow it, the cloud left where the chain put
        it) and the points near its datums (:attr:`cell.analysis.alignment.Alignment.datum_near`)."""
        try:
            found = self.aligner.align(points_mm)
        except AlignmentError as exc:
            return stored_points(points_mm), {"method": self.recipe.alignment.method, "error": str(exc)}, None
        moved = stored_points(transform_points(found.T, points_mm), in_place=True)  # (a new array)
        return moved, found.to_json(), found.datum_near

    def _aligned_cloud(
        self,
        run: RunFolder,
        merged: MergedCloud,
        shares: MergeShares,
        refined: ViewRefinement,
        merging: dict[str, Any],
        pool: Executor,
    ) -> tuple[RegisteredCloud, float | None]:
        """The merged cloud aligned (:meth:`_aligned`), without the table its seam cuts, with its error map,
        coverage and points' u, and the judged points' link radius when the judge needs it; its
        registration record: the seam's and the points' counts, ``merging`` (how the views were merged),
        the alignment and the u budget. On ``pool``'s two threads beside this one: the coverage beside the
        error map, the table seam and then the judged points' link radius beside the points' u (whose chunks
        every free thread computes), the u budget's three statistics side by side."""
        points_P, alignment, datum_near = self._aligned(merged.points_mm)
        T_align = np.asarray(alignment["T_P_cloud"]) if "T_P_cloud" in alignment else None
        prior = pose_uncertainty_prior(self.cfg, self._refinement[2] if self._refinement else {})
        tolerance = self._tolerance()
        coverage = pool.submit(self.inspectable_coverage, run, T_align)
        error_map = signed_distance(self.nominal_P, points_P)  # its faces' normals are the u's too
        seam_cut = pool.submit(
            table_seam,
            points_P,
            self.T_W_P,
            self.settings.table_margin_mm,
            self.nominal_P,
            deviation_mm=error_map.deviation_mm,
        )

        def judged_points() -> tuple[NDArray[np.bool_] | None, NDArray[np.float64], float | None]:
            """Which points the seam leaves (None: all of them, not copied), they, and, when one is outside
            the tolerance, their link radius (what the judge would find: out-of-tolerance regions need it)."""
            cut = seam_cut.result()
            keep = ~cut if cut.any() else None
            kept = points_P if keep is None else np.take(points_P, np.flatnonzero(keep), axis=0)
            deviation = error_map.deviation_mm if keep is None else error_map.deviation_mm[keep]
            return keep, kept, default_link_radius(kept) if tolerance.outside(deviation).any() else None

        judged = pool.submit(judged_points)
        unc = registered_cloud_uncertainty(
            merged,
            shares.shares(merged),
            shares.decode(merged),
            refined,
            prior,
            transform_vectors(self.T_W_P, self.nominal_P.face_normals),
            error_map.face,
            self.T_W_P,
            alignment,
            self.aligner.datums,
            pool,
            datum_near,
        )
        budget = unc.budget(pool)  # its statistics side by side
        keep, points_P, link_radius_mm = judged.result()
        u_mm = unc.u_mm if keep is None else unc.u_mm[keep]
        error_map = error_map if keep is None else error_map.take(keep)
        registration = {
            "table_seam_points": 0 if keep is None else int((~keep).sum()),
            "n_points": int(len(points_P)),
            **merging,
            "alignment": alignment,
            "uncertainty": {
                **budget,
                "calibration": self.calibration_residual,
                "poses": prior.get("prior"),
            },
        }
        return RegisteredCloud(registration, points_P, error_map, coverage.result(), u_mm), link_radius_mm

    def _tolerance(self) -> Tolerance:
        """The recipe's tolerance band (mm)."""
        return Tolerance(self.recipe.tolerance.lower, self.recipe.tolerance.upper)

    @property
    def nominal_P(self) -> NominalMesh:
        """The nominal in the part frame, as the error map needs it (built once)."""
        with self._lock:
            if self._nominal_P is None:
                self._nominal_P = NominalMesh.from_trimesh(
                    self.nominal_W.copy().apply_transform(invert(self.T_W_P))
                )
            return self._nominal_P

    def _registered(self, run: RunFolder) -> RegisteredCloud:
        """The registered cloud: this process's registration, else results/cloud.ply (a run reported before,
        or registered by an older version), else registered again from the views."""
        if self._cloud is not None:
            return self._cloud
        legacy = run.results_dir / "points_P.npy"  # a run registered before the cloud was stored once
        registration = Checkpoint.from_json(run.load_checkpoint()).registration or {}
        # as cloud.ply stores them (float32): a no-op on a cloud written so; an older float64 cloud is judged
        # as the report will store it, so the next rebuild gives the same figures
        if legacy.is_file():
            return RegisteredCloud(registration, stored_points(np.load(legacy)))
        if (ply := run.results_dir / "cloud.ply").is_file():
            u = read_ply_field(ply, "uncertainty")
            u_mm = None if u is None else decode_uncertainty(u)
            return RegisteredCloud(registration, stored_points(read_ply_points(ply)), uncertainty_mm=u_mm)
        self.register(run, Checkpoint.from_json(run.load_checkpoint()).views)
        assert self._cloud is not None  # a registration without points never reaches the report
        return self._cloud

    def inspectable_coverage(self, run: RunFolder, T_P_cloud: NDArray[np.float64] | None = None) -> Coverage:
        """Coverage of the inspectable nominal surface (what the planner can see: not the underside on the
        table) at the recipe's point density, from the measured views moved by the alignment ``T_P_cloud``."""
        plan, st = self.plan_model, self.recipe.plan
        s = plan.surface
        done, found = self.refinement(run)
        A = np.eye(4) if T_P_cloud is None else self.T_W_P @ T_P_cloud @ invert(self.T_W_P)
        views = [(self.views.get(run, i).eval_tree, A @ T) for i, T in zip(done, found.T, strict=True)]
        ins = s.inspectable  # the other samples are left out, not counted
        covered = covered_by_views(s, views, st.point_density_per_mm2, st.coverage_radius_mm, samples=ins)
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
        """Judge the registered cloud and publish the verdict: results/report.json, before anything else is
        written (:meth:`render` writes the page, the cloud and, when ``csv``, deviations.csv). Returns the
        verdict and the key figures."""
        inp = self._report_input(run, registration)
        doc = write_verdict(run.results_dir, inp, pictures=self.settings.pictures)
        self._judged = (inp, doc, csv)
        return {
            "verdict": doc.get("verdict"),
            "n_points": doc.get("n_points"),
            "coverage": doc.get("coverage"),
            "deviation": doc.get("deviation"),
        }

    def render(self, run: RunFolder) -> dict[str, Any]:
        """The report after its verdict: results/cloud.ply (every point with its deviation), report.html (its
        pictures and 3D view), deviations.csv when :meth:`report` was asked for it. A resumed run judges the
        cloud again (the same points, so the same page) and keeps the verdict report.json holds."""
        if self._judged is None:
            checkpoint = Checkpoint.from_json(run.load_checkpoint())
            inp = self._report_input(run, checkpoint.registration or {})
            doc = json.loads((run.results_dir / "report.json").read_text())
            self._judged = (inp, doc, False)
        inp, doc, csv = self._judged
        written = write_page(run.results_dir, doc, inp, pictures=self.settings.pictures, csv=csv)
        (run.results_dir / "points_P.npy").unlink(missing_ok=True)  # cloud.ply now holds its points as judged
        return {"files": written}

    def _report_input(self, run: RunFolder, registration: dict[str, Any]) -> ReportInput:
        """The judged registered cloud (:meth:`_judge`, done by the registration when this process made it)
        with the run's context: the calibration, the evaluation and why the verdict is incomplete."""
        cloud = self._registered(run)
        # the judged cloud's copy (its judged arrays and figures shared, not recomputed): the context is set
        # on it, the cloud's own stays as the judge made it
        inp = copy.copy(cloud.judged if cloud.judged is not None else self._judge(run, cloud))
        checkpoint = Checkpoint.from_json(run.load_checkpoint())
        evaluation = checkpoint.evaluation.to_json() if checkpoint.evaluation is not None else {}
        alignment = registration.get("alignment") or {"method": "kinematic"}
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
        if (no_u := self._decision(cloud)[2]) is not None:
            reasons.append(no_u)
        inp.incomplete_reasons, inp.calibration = reasons, calibration
        inp.metadata = {
            "part": self.part_name,
            "cad": Path(self.recipe.part.cad).name,
            "views": [
                {"patch": v.patch, "source": v.source, "iteration": v.iteration} for v in checkpoint.views
            ],
            "registration": registration,
            "evaluation": evaluation,
            "plan": inp.metadata["plan"],  # predicted coverage, min_coverage, unseen_surfaces, warnings
            "geometry_source": self.geometry_source,
            "run": run_record(run, self.cfg.name),
        }
        return inp

    def _decision(
        self, cloud: RegisteredCloud
    ) -> tuple[DecisionRule, NDArray[np.float64] | None, str | None]:
        """The rule the cloud is judged by, its points' u (None: not known) and, when the recipe's rule needs
        the u a cloud registered before points carried it lacks, why the verdict is incomplete."""
        u = cloud.uncertainty_mm
        if u is not None and np.isfinite(u).any():
            return self.decision, u, None
        if self.decision.rule == "guarded":
            return (
                DecisionRule(),
                None,
                "the guarded decision rule needs the points' uncertainty; this run has none",
            )
        return self.decision, None, None

    def _judge(
        self,
        run: RunFolder,
        cloud: RegisteredCloud,
        link_radius_mm: float | None = None,
        pool: Executor | None = None,
    ) -> ReportInput:
        """The registered cloud judged (:func:`cell.analysis.judge.judge`, its :meth:`ReportInput.figures`
        computed) without the run's context, which :meth:`_report_input` adds: what depends on the cloud, its
        registration and the recipe alone, so the registration does it beside the evaluation and a report
        rebuilt from cloud.ply does the same. ``link_radius_mm``: the cloud's
        :func:`cell.analysis.report.default_link_radius` when the caller found it already; ``pool``: threads
        for the figures (:meth:`ReportInput.figures`). Its metadata holds the plan's feedback (what no
        reachable viewpoint sees) alone."""
        registration = cloud.registration
        excluded = {
            "unregistered_view_measured_elsewhere_points": int(
                registration.get("refinement", {}).get("unregistered_points_dropped", 0)
            ),
            "table_seam_points": int(registration.get("table_seam_points", 0)),
        }
        for view in self.views.completed(run):
            for reason, n in view.summary.get("excluded", {}).items():
                excluded[f"{reason}_points"] = excluded.get(f"{reason}_points", 0) + int(n)
        alignment = registration.get("alignment") or {"method": "kinematic"}
        T_align = np.asarray(alignment["T_P_cloud"]) if "T_P_cloud" in alignment else None
        decision, u, _ = self._decision(cloud)
        plan = plan_feedback(self.plan_model, self.recipe)  # what no reachable viewpoint sees, for the reader
        inp = judge(
            self.nominal_P,
            cloud.points_P,
            self._tolerance(),
            n_points_input=int(registration.get("n_points_views", len(cloud.points_P))),
            regions=[region_from_config(spec) for spec in self.recipe.regions],
            min_defect_points=self.settings.min_defect_points,
            excluded=excluded,
            coverage=cloud.coverage or self.inspectable_coverage(run, T_align),
            min_coverage=self.recipe.min_coverage,
            link_radius_mm=link_radius_mm,
            warnings=[*alignment.get("warnings", []), *plan.warnings],
            alignment=alignment,
            uncertainty_mm=u,
            decision=decision,
            uncertainty=registration.get("uncertainty"),
            metadata={"plan": plan.to_json()},
            error_map=cloud.error_map,
        )
        inp.figures(pool)
        return inp
