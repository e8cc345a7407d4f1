"""The measured views of an inspection as its whole-cloud steps use them: each view read and analysed once.

The decode worker writes a view's folder whole while the robot moves on (:mod:`cell.controller`); with the
points it writes the view's own analysis, the local planes of its evaluation subset (``planes.npz``), into the
same folder, so a view counts as done only once its analysis is durable too. The job keeps every completed
view in memory (:class:`ViewStore`): what the decode produced, or, after a resume, what the folder holds, read
once. Both are the same numbers (the points as stored, the planes as saved), so a resumed run computes what an
uninterrupted one does.

The refinement, the accuracy map and the cut of unregistered views move views by small rigid corrections;
they query each view's KD-tree in the view's own (kinematic) frame with the query points moved into it (a
rigid motion keeps distances), so no tree is rebuilt when the poses change (:class:`ViewResult.eval_tree`).

Per-point arrays travel with the points (:class:`cell.view_files.ViewPoints`: quality, oblique and whatever a
view stores per point), in pixel order, so a new per-point field reaches the merge without a change here.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.analysis.view_refinement import LocalPlanes, estimate_normals
from cell.planning.measured import DefectRegion
from cell.runs import RunFolder
from cell.view_files import (
    STEP_MM,
    ViewPoints,
    load_eval_points,
    load_eval_uncertainty,
    load_view_points,
    stored_points,
)

PLANES_FILE = "planes.npz"  # the evaluation subset's local planes (float64 centroids and normals, bool ok)
REGIONS_FILE = "defects.npz"  # the hole regions (format 2: 0.1 um steps; format 1: float64)
REGIONS_FORMAT = 2
# the views' full point sets kept in memory at most (33 bytes a point: a 1024x768 view ~15 MB, a 5 MP view
# 73-89 MB); beyond it the oldest views' points are dropped and read from their folders when needed (by the
# registration, one view at a time). A fixed figure, not one that grows with the camera: the 1024x768 cell's
# dozen views (0.19 GB) stay held, a 5 MP camera's dozen (0.9 GB) would sit beside the registration's own
# ~2 GB at its peak (docs/benchmarks.md, "Peak memory of a whole inspection")
POINTS_IN_MEMORY_BYTES = 256_000_000
# and a view's points only while they are at most this big, the newest view's too: a 5 MP view's would save
# the registration one read of its folder (~0.5 s CPU) for up to 90 MB held through the next view's decode
# and beside the registration's peak (issue 16, item 5); the 1024x768 cell's (~15 MB) are all kept
POINTS_HELD_VIEW_MAX_BYTES = 32_000_000


@dataclass
class ViewResult:
    """One completed view (all in {W}, mm, at the pose the kinematic chain gave it): the stored points with
    their per-point arrays in pixel order (:meth:`points`; held in memory while the store's budget allows),
    the evaluation subset (one point per ``eval_voxel_mm`` voxel) and its local planes, the camera pose and
    the hole regions, and the view's ``view.json`` summary."""

    index: int
    held: ViewPoints | None  # the full points while held in memory, else read from ``folder``
    eval_W: NDArray[np.float64]
    planes: LocalPlanes
    regions: list[DefectRegion]
    summary: dict[str, Any]
    folder: Path | None = None  # where the view is stored (None: while it is being written)
    eval_u: NDArray[np.float32] | None = None  # the evaluation subset's decode u (mm; None: not stored)

    def points(self) -> ViewPoints:
        """The full points with their per-point arrays: held, or read from the view's folder."""
        held = self.held
        if held is not None:
            return held
        assert self.folder is not None  # a view is dropped from memory only once stored
        return load_view_points(self.folder)

    @property
    def held_bytes(self) -> int:
        held = self.held
        if held is None:
            return 0
        u = 0 if held.uncertainty is None else held.uncertainty.nbytes
        return int(held.points_W.nbytes + held.quality.nbytes + held.oblique.nbytes + u)

    @property
    def T_W_C(self) -> NDArray[np.float64]:
        return np.asarray(self.summary["T_W_C"], dtype=np.float64)

    @property
    def camera_W(self) -> NDArray[np.float64]:
        """The camera centre in {W} (mm)."""
        return self.T_W_C[:3, 3]

    @cached_property
    def eval_tree(self) -> cKDTree:
        """KD-tree of the evaluation subset in this view's own frame (query with points moved into it)."""
        return cKDTree(self.eval_W)


def save_planes(view_dir: Path, planes: LocalPlanes) -> None:
    """Write the local planes of a view's evaluation subset into its (temporary) folder."""
    with open(view_dir / PLANES_FILE, "wb") as f:
        np.savez(f, centroid=planes.centroid, normal=planes.normal, ok=planes.ok)


def load_planes(view_dir: Path, eval_W: NDArray[np.float64]) -> LocalPlanes:
    """The stored local planes of a view; computed from ``eval_W`` for a folder written before they were
    stored (the folder is left as it is)."""
    path = view_dir / PLANES_FILE
    if not path.is_file():
        return estimate_normals(eval_W)
    with np.load(path) as z:
        return LocalPlanes(z["centroid"], z["normal"], z["ok"])


def remove_planes(run: RunFolder) -> int:
    """Remove the views' stored local planes (``planes.npz``) of a finished run and return the bytes freed.

    They are the decode worker's cache for a resumed run (:func:`load_planes` computes the same from the
    stored evaluation points when the file is absent): 4.5-6.3 MB a pillar view as float64, 44 MB of a 12-view
    run, more than its cloud. A finished run is not resumed, and whatever reads its views again (a rebuilt
    report) gets the same planes from the points, so no number is lost."""
    freed = 0
    views = run.path / "views"
    for path in sorted(views.glob(f"*/{PLANES_FILE}")) if views.is_dir() else []:
        size = path.stat().st_size
        path.unlink(missing_ok=True)
        freed += size
    return freed


def save_regions(path: Path, regions: list[DefectRegion]) -> None:
    """A view's hole regions (reason, boundary and interior points in {W}, pixel count) as one npz (format
    2): each point array as int32 differences of :data:`STEP_MM` steps (0.1 um, as the view's points;
    neighbouring pixels' nominal points lie close), a sixth of the deflated float64 of format 1. What is
    read back is :func:`stored_regions` of ``regions``."""
    arrays: dict[str, Any] = {
        "format": np.asarray(REGIONS_FORMAT, np.int32),
        "step_mm": np.asarray(STEP_MM, np.float64),
        "reasons": np.array([r.reason for r in regions], dtype="U16"),
        "pixels": np.array([r.pixels for r in regions], dtype=np.int64),
    }
    for k, r in enumerate(regions):
        arrays[f"boundary_{k}"] = _step_deltas(r.boundary_W)
        arrays[f"points_{k}"] = _step_deltas(r.points_W)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def stored_regions(regions: list[DefectRegion]) -> list[DefectRegion]:
    """The regions as :func:`save_regions` stores them (points rounded to :data:`STEP_MM`), which is what a
    resumed run reads back: an uninterrupted run keeps these so that both compute the same."""
    return [
        DefectRegion(r.reason, stored_points(r.boundary_W), stored_points(r.points_W), r.pixels)
        for r in regions
    ]


def _step_deltas(points_W: NDArray[np.float64]) -> NDArray[np.int32]:
    steps = np.round(stored_points(points_W) / STEP_MM).astype(np.int64)
    return np.diff(steps, axis=0, prepend=np.zeros((1, 3), np.int64)).astype(np.int32)


def load_regions(path: Path) -> list[DefectRegion]:
    """A view's hole regions, from format 2 or from format 1 (float64 points, no ``format`` entry)."""
    with np.load(path) as data:
        if "format" in data.files:
            step = float(data["step_mm"])

            def points(name: str) -> NDArray[np.float64]:
                return np.asarray(np.cumsum(data[name], axis=0, dtype=np.int64) * step, dtype=np.float64)
        else:

            def points(name: str) -> NDArray[np.float64]:
                return np.asarray(data[name], dtype=np.float64)

        return [
            DefectRegion(str(reason), points(f"boundary_{k}"), points(f"points_{k}"), int(px))
            for k, (reason, px) in enumerate(zip(data["reasons"], data["pixels"], strict=True))
        ]


def load_view_result(view_dir: Path, index: int) -> ViewResult:
    """A completed view read from its folder (any stored format, :mod:`cell.view_files`)."""
    eval_W = load_eval_points(view_dir)
    return ViewResult(
        index,
        load_view_points(view_dir),
        eval_W,
        load_planes(view_dir, eval_W),
        load_regions(view_dir / REGIONS_FILE),
        json.loads((view_dir / "view.json").read_text()),
        view_dir,
        load_eval_uncertainty(view_dir),
    )


class ViewStore:
    """The completed views of the run a job works on, each read once: :meth:`add` from the decode worker
    (the view as it is being written), :meth:`get` reads a view not added (a run resumed by a new process)."""

    def __init__(
        self,
        points_budget_bytes: int = POINTS_IN_MEMORY_BYTES,
        held_view_max_bytes: int = POINTS_HELD_VIEW_MAX_BYTES,
    ) -> None:
        self._views: dict[int, ViewResult] = {}
        self._run: Path | None = None
        self._lock = threading.Lock()
        self.points_budget_bytes = points_budget_bytes
        self.held_view_max_bytes = held_view_max_bytes

    def _for(self, run: RunFolder) -> None:
        """Forget the views of another run folder: a job works on one run (the first one it is asked about
        claims the views its decode produced)."""
        if self._run is not None and self._run != run.path:
            self._views.clear()
        self._run = run.path

    def add(self, view: ViewResult) -> None:
        """Keep a view the decode worker produced (its folder is committed right after; a view whose commit
        fails pauses the run, and the next process reads the folders)."""
        with self._lock:
            self._views[view.index] = view
            self._within_budget(keep=view.index)

    def get(self, run: RunFolder, index: int) -> ViewResult:
        with self._lock:
            self._for(run)
            found = self._views.get(index)
        if found is None:
            found = load_view_result(run.view_dir(index), index)
            with self._lock:
                self._views[index] = found
                self._within_budget(keep=index)
        return found

    def _within_budget(self, keep: int) -> None:
        """Drop the full points of views bigger than ``held_view_max_bytes`` (the newest one's too: only the
        registration reads them again, one view at a time, after the last view's folder is committed), and of
        the views added first until the held ones fit the budget (the newest view stays then)."""
        held = sum(v.held_bytes for v in self._views.values())
        for index, view in self._views.items():
            big = view.held_bytes > self.held_view_max_bytes
            if held <= self.points_budget_bytes and not big:
                continue
            if (index != keep or big) and view.held is not None and view.folder is not None:
                held -= view.held_bytes
                view.held = None

    def completed(self, run: RunFolder) -> list[ViewResult]:
        """The views of ``run`` whose folders exist whole, in index order."""
        return [self.get(run, i) for i in run.completed_views()]
