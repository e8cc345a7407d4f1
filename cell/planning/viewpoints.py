"""The bounding-box viewpoint search (dissertation Figs. 3.4-3.5, eq 3.3) for one patch of surface samples.

A patch's samples are boxed in a frame whose w axis is the patch's mean normal (u, v: principal axes of the
points in the tangent plane). The box is tested against the task constraints: its footprint (L x W) must fit
the field of view for some roll about the view axis, its height H the focus range. Candidate viewpoints sit on
the box's centre line at the stand-off, looking along -w, at 8 rolls (the roll decides on which side the
projector stands, so it decides self-shadowing); each candidate is scored by the share of the patch it
measures (projector constraints first, then camera, with ray-cast occlusion for both). When no roll measures
``patch_accept`` of the patch, or the box is too large, the patch is split in two across its longest axis and
each half is searched again (Fig. 3.5). Unreachable candidates are re-posed: other rolls first, then the view
direction tilted by 15, 30 and 45 degrees about the box centre (45: the view that reaches a low vertical
face, such as the side of a flat part, from above the envelope floor).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.geometry import Pose
from cell.planning.reach import ReachChecker
from cell.planning.sensor_model import SensorModel
from cell.planning.surface import PartSurface

Array = NDArray[np.float64]
ROLLS = np.deg2rad(np.arange(0, 360, 45))
TILTS = np.deg2rad((15.0, 30.0, 45.0))
TILT_AZIMUTHS = np.deg2rad(np.arange(0, 360, 60))
MIN_SAMPLES = 6


@dataclass
class Viewpoint:
    """A planned camera pose and what it is for. ``measures`` are the sample indices it is predicted to
    measure within its patch (over all samples see :func:`cell.planning.coverage.predicted_masks`)."""

    T_W_C: Pose
    T_B_T: Pose
    patch: str
    source: str  # "f0", "f0-fill", "g_kS", "g_kR", "g_kA"
    patch_fraction: float
    measures: NDArray[np.int64] = field(repr=False, default_factory=lambda: np.zeros(0, dtype=np.int64))


@dataclass
class Box:
    """Bounding box of a patch: centre (world mm), axes u, v, w (columns), extents L, W, H (mm)."""

    centre: Array
    axes: Array
    extents: Array


def bounding_box(points: Array, normals: Array, weights: Array) -> Box:
    """Box with w along the mean normal and u, v the principal in-plane axes of the points."""
    w = (normals * weights[:, None]).sum(axis=0)
    w = w / np.linalg.norm(w) if np.linalg.norm(w) > 1e-9 else np.array([0.0, 0.0, 1.0])
    ref = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(w, ref)
    a /= np.linalg.norm(a)
    b = np.cross(w, a)
    c = points - points.mean(axis=0)
    uv = np.column_stack([c @ a, c @ b])
    if len(points) >= 2:
        evals, evecs = np.linalg.eigh(uv.T @ uv)
        e = evecs[:, np.argmax(evals)]
    else:
        e = np.array([1.0, 0.0])
    u = e[0] * a + e[1] * b
    v = np.cross(w, u)
    axes = np.column_stack([u, v, w])
    local = points @ axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    return Box(axes @ (0.5 * (lo + hi)), axes, hi - lo)


class PatchPlanner:
    """Finds viewpoints for patches of one part, logging each decision (dicts with a ``reason``)."""

    def __init__(
        self, sensor: SensorModel, surface: PartSurface, reach: ReachChecker, log: list[dict[str, Any]]
    ):
        self.sensor = sensor
        self.surface = surface
        self.reach = reach
        self.log = log
        self.candidates: list[Pose] = []  # every reachable pose evaluated (the set-cover baseline's pool)
        st = sensor.settings
        fx, fy = sensor.fov_mm
        self.fov = (fx * st.fov_margin, fy * st.fov_margin)
        self.dof = sensor.dof_mm * st.dof_margin

    def roll_fits(self, box: Box) -> NDArray[np.bool_]:
        L, W = box.extents[0], box.extents[1]
        c, s = np.abs(np.cos(ROLLS)), np.abs(np.sin(ROLLS))
        return (L * c + W * s <= self.fov[0]) & (L * s + W * c <= self.fov[1])

    def plan(self, idx: NDArray[np.int64], name: str, source: str) -> list[Viewpoint]:
        """Viewpoints covering the samples ``idx`` (recursive split on failure)."""
        s = self.surface
        pts, nrm, area = s.points[idx], s.normals[idx], s.area[idx]
        total = float(area.sum())
        box = bounding_box(pts, nrm, area)
        can_split = len(idx) >= 2 * MIN_SAMPLES and total > 2 * self.sensor.settings.min_patch_area_mm2
        fits = self.roll_fits(box)
        too_deep = box.extents[2] > self.dof
        if (not fits.any() or too_deep) and can_split:
            why = (
                "footprint exceeds the field of view" if not fits.any() else "height exceeds the focus range"
            )
            self.log.append(
                {"event": "split", "patch": name, "reason": why, "box_mm": np.round(box.extents, 1).tolist()}
            )
            return self._split(idx, box, name, source)
        best = self._best_pose(idx, box, fits if fits.any() else np.ones(len(ROLLS), bool))
        accept = self.sensor.settings.patch_accept
        if best is not None and (best[1] >= accept or (not can_split and best[1] > 0)):
            T, frac, meas, how = best
            self.log.append(
                {
                    "event": "viewpoint",
                    "patch": name,
                    "source": source,
                    "reason": how,
                    "patch_fraction": round(frac, 4),
                    "samples": int(len(idx)),
                }
            )
            return [Viewpoint(T, self.reach.target(T), name, source, frac, idx[meas])]
        if can_split:
            got = 0.0 if best is None else best[1]
            self.log.append(
                {
                    "event": "split",
                    "patch": name,
                    "reason": f"best reachable viewpoint measures {got:.2f} of the patch < {accept:.2f}",
                    "box_mm": np.round(box.extents, 1).tolist(),
                }
            )
            return self._split(idx, box, name, source)
        self.log.append(
            {
                "event": "unplanned",
                "patch": name,
                "reason": "no reachable viewpoint measures any of this small patch",
                "area_mm2": round(total, 1),
            }
        )
        return []

    def _split(self, idx: NDArray[np.int64], box: Box, name: str, source: str) -> list[Viewpoint]:
        local = (self.surface.points[idx] - box.centre) @ box.axes
        # split across the longer in-plane axis; when the box is only too deep, across the one along which
        # the height varies most (a fold line)
        axis = 0 if box.extents[0] >= box.extents[1] else 1
        coord = local[:, axis]
        # pieces of equal length that each fit the long side of the field (two at least, as in Fig. 3.5)
        pieces = max(2, int(np.ceil(box.extents[axis] / max(self.fov))))
        cuts = np.quantile(coord, np.linspace(0, 1, pieces + 1)[1:-1]) if pieces > 2 else [np.median(coord)]
        if box.extents[axis] > max(self.fov):
            cuts = coord.min() + box.extents[axis] * np.arange(1, pieces) / pieces
        part = np.searchsorted(np.asarray(cuts), coord)
        if len(np.unique(part)) < 2:
            part = (np.arange(len(idx)) >= len(idx) // 2).astype(int)
        out: list[Viewpoint] = []
        for k in np.unique(part):
            out += self.plan(idx[part == k], f"{name}.{k}", source)
        return out

    def _best_pose(
        self, idx: NDArray[np.int64], box: Box, rolls_ok: NDArray[np.bool_]
    ) -> tuple[Pose, float, NDArray[np.bool_], str] | None:
        """Best reachable (pose, patch fraction, measured mask, how) over rolls, then tilts if needed."""
        s, sensor = self.surface, self.sensor
        pts, nrm, area = s.points[idx], s.normals[idx], s.area[idx]
        total = area.sum()
        view = -box.axes[:, 2]
        unreachable: list[str] = []

        rolls = ROLLS[rolls_ok]

        def evaluate(
            directions: list[tuple[Array, str]],
        ) -> list[tuple[Pose, float, NDArray[np.bool_], str] | None]:
            """The best roll of each direction, the reach of all of them checked in one batch (its IK)."""
            poses = []
            for direction, _ in directions:
                for r in rolls:
                    T = sensor.pose(box.centre, direction, float(r), box.axes[:, 0])
                    poses.append(
                        sensor.bisector_pose(T, box.centre) if sensor.settings.aim == "bisector" else T
                    )
            checks = iter(self.reach.check_many(poses))  # cheaper than the visibility test: filter first
            out: list[tuple[Pose, float, NDArray[np.bool_], str] | None] = []
            for k, (_, label) in enumerate(directions):
                cands = []
                for r, T in zip(rolls, poses[k * len(rolls) : (k + 1) * len(rolls)], strict=True):
                    ok, why = next(checks)
                    if not ok:
                        unreachable.append(why)
                        continue
                    m = sensor.measurable(T, pts, nrm, s.occluder)
                    self.candidates.append(T)
                    cands.append(
                        (float(area[m].sum() / total), T, m, f"{label}, roll {np.rad2deg(r):.0f} deg")
                    )
                if not cands:
                    out.append(None)
                    continue
                frac, T, m, how = max(cands, key=lambda c: c[0])
                out.append((T, frac, m, how))
            return out

        best = evaluate([(view, "on the box centre line")])[0]
        accept = sensor.settings.patch_accept
        if best is None or best[1] < accept:
            # re-pose: tilt the view about the box centre
            for tilt in TILTS:
                directions = []
                for az in TILT_AZIMUTHS:
                    axis = np.cos(az) * box.axes[:, 0] + np.sin(az) * box.axes[:, 1]
                    d = np.cos(tilt) * view + np.sin(tilt) * np.cross(axis, view)
                    directions.append(
                        (d, f"tilted {np.rad2deg(tilt):.0f} deg (azimuth {np.rad2deg(az):.0f})")
                    )
                for got in evaluate(directions):  # every azimuth of a tilt is tried before judging
                    if got is not None and (best is None or got[1] > best[1]):
                        best = got
                if best is not None and best[1] >= accept:
                    break
        if best is None and unreachable:
            self.log.append(
                {"event": "unreachable", "reason": unreachable[0], "candidates": len(unreachable)}
            )
        return best
