"""Refine the views' poses against each other where they overlap (multi-view registration, dissertation
4.1.3).

The kinematic chain puts every view into {W} with the robot's pose error and whatever the hand-eye calibration
left: a few tenths of a millimetre that differ from view to view, so two views of one spot disagree by more
than the sensor's noise and the merged surface gets a step where they meet. Each view i gets a small rigid
correction ``T_i`` ({W} -> {W}) that minimises, jointly over all views,

    sum over overlapping point pairs  (n_j . (T_i p - T_j q))^2 / sigma_pair^2          (point-to-plane)
  + sum over views                    |x_i|^2 / sigma_prior^2                           (kinematic prior)

where x_i = (omega_i * lever, tau_i) is the linearised correction (rotation scaled by a lever arm, mm). The
prior is what the cell knows about its own pose uncertainty (``RegistrationConfig``): it fixes the gauge (the
views as a whole stay where the kinematic chain put them, so the part's placement is judged by the recipe's
alignment, not here) and holds a view still along directions its overlaps do not constrain (a view that
overlaps only a flat wall may not slide along it). The views are registered to *each other*, never to the CAD,
so a deviation of the part cannot be fitted away. Pairs are matched by nearest neighbour with consistent
normals, the match radius shrinks over the iterations, and residuals beyond 3 robust sigmas are dropped.

Written by hand because the joint solve with a per-view prior is a few lines of normal equations (6 unknowns
per view); Open3D's pose graph is not a dependency and does not take a kinematic prior.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cell.geometry import Pose, incidence_cos, make_pose, transform_points

Array = NDArray[np.float64]
SAME_NORMAL_COS = float(np.cos(np.deg2rad(20.0)))  # across an edge or the other skin of a sheet: no match
MAX_PAIRS_PER_OVERLAP = 2000  # matches used per ordered view pair (a random, seeded sample)
EFFECTIVE_PAIRS = 100  # independent observations one overlap is worth (see the weight in refine_views)
MAX_INCIDENCE_DEG = 70.0  # pairs seen at more than this from the normal by either view are not used
MIN_INCIDENCE_COS = float(np.cos(np.deg2rad(MAX_INCIDENCE_DEG)))
MIN_VIEW_PAIRS = 500  # a view held by fewer (incidence-weighted) pairs is not refined
MIN_PAIRS = 50  # an overlap with fewer matches does not constrain the views


@dataclass
class ViewRefinement:
    """Per-view corrections ``T`` ({W} -> {W}), and what the overlaps said: rms of the point-to-plane gaps
    before and after (mm), the number of views each view overlapped with, and the views no overlap reached
    (left at the kinematic pose)."""

    T: list[Pose]
    rms_before_mm: float
    rms_after_mm: float
    overlaps: list[int]
    unregistered: list[int] = field(default_factory=list)
    # what the overlaps of the last solve told about the corrections x_i = (omega_i * lever_mm, tau_i) about
    # ``centre_mm``: their (6n, 6n) information matrix, without the prior and the pinning of the views held
    # at their kinematic pose (None when nothing was solved); cell.analysis.uncertainty turns it into the
    # views' pose covariance under a prior
    information: Array | None = None
    centre_mm: Array | None = None
    lever_mm: float = 1.0

    def correction_mm(self, points: list[Array]) -> list[float]:
        """The largest motion of each view's points under its correction (mm)."""
        return [
            float(np.linalg.norm(transform_points(T, p) - p, axis=1).max()) if len(p) else 0.0
            for T, p in zip(self.T, points, strict=True)
        ]

    def to_json(self, points: list[Array]) -> dict[str, Any]:
        moved = self.correction_mm(points)
        return {
            "rms_before_mm": round(self.rms_before_mm, 5),
            "rms_after_mm": round(self.rms_after_mm, 5),
            "max_correction_mm": round(max(moved, default=0.0), 4),
            "corrections_mm": [round(m, 4) for m in moved],
            "unregistered_views": self.unregistered,
        }


@dataclass(frozen=True)
class LocalPlanes:
    """Each point's local plane from its ``k`` nearest neighbours: the neighbourhood's centroid (mm), unit
    normal (PCA) and whether it is planar enough to trust (smallest eigenvalue under 10 % of the middle one).
    Gaps are measured to the plane through the centroid, not to the noisy point: the PCA normal is
    estimated from that point's own noise, and the correlation between the two would bias the solve."""

    centroid: Array
    normal: Array
    ok: NDArray[np.bool_]


def estimate_normals(points: Array, k: int = 20) -> LocalPlanes:
    """The local planes of ``points`` (mm) by PCA of each point's ``k`` nearest neighbours."""
    n = len(points)
    if n < k:
        return LocalPlanes(points.copy(), np.zeros((n, 3)), np.zeros(n, dtype=bool))
    _, idx = cKDTree(points).query(points, k=k)
    centroid = points[idx].mean(axis=1)
    nb = points[idx] - centroid[:, None, :]
    cov = np.einsum("nki,nkj->nij", nb, nb) / k
    w, v = np.linalg.eigh(cov)
    return LocalPlanes(centroid, v[:, :, 0], w[:, 0] < 0.1 * np.maximum(w[:, 1], 1e-12))


def _observable(J: Array, ratio: float = 1e-4) -> Array:
    """Projector onto the motions an overlap observes. On a plane a slide along it changes no gap, yet the
    normals' estimation noise gives it a small, spurious information that would couple the overlap's normal
    offset into a slide; directions whose information is under ``ratio`` of the strongest are left to the
    prior (a truncated eigen-decomposition of J^T J)."""
    lam, U = np.linalg.eigh(J.T @ J)
    Uk = U[:, lam >= ratio * lam[-1]]
    return Uk @ Uk.T


def _candidates(
    points: Array, ok: NDArray[np.bool_], box: tuple[Array, Array], margin: float, rng: Any
) -> NDArray[np.int64]:
    """Indices of the trusted ``points`` inside the other view's bounding ``box`` (grown by ``margin``): where
    an overlap can be; at most twice the matches an overlap uses, drawn at random."""
    inside = ok & np.all((points >= box[0] - margin) & (points <= box[1] + margin), axis=1)
    src = np.flatnonzero(inside)
    if len(src) > 2 * MAX_PAIRS_PER_OVERLAP:
        src = rng.choice(src, 2 * MAX_PAIRS_PER_OVERLAP, replace=False)
    return src


def _boxes_overlap(a: tuple[Array, Array], b: tuple[Array, Array], margin: float) -> bool:
    """Whether two (min, max) boxes overlap when grown by ``margin``."""
    return bool(np.all(a[0] - margin <= b[1]) and np.all(b[0] - margin <= a[1]))


def _apply(x: NDArray[np.float64], centre: Array, lever_mm: float) -> Pose:
    """The rigid motion of a linearised correction (rotation vector * lever, translation) about ``centre``."""
    R = Rotation.from_rotvec(x[:3] / lever_mm).as_matrix()
    return make_pose(R, centre + x[3:] - R @ centre)


def refine_views(
    views: list[Array],
    sigma_t_mm: float | Array,
    sigma_r_rad: float | Array,
    noise_mm: float = 0.05,
    radii_mm: tuple[float, ...] = (2.0, 1.0, 0.6),
    seed: int = 0,
    planes: list[LocalPlanes] | None = None,
    cameras: list[Array] | None = None,
) -> ViewRefinement:
    """Corrections for ``views`` (points in {W}, mm; one array per view) under the prior (``sigma_t_mm``,
    ``sigma_r_rad``: 1-sigma translation and rotation of a view's pose, one for all or one per view) with
    point gaps of ``noise_mm`` noise,
    matching within each of ``radii_mm`` in turn (one linearised solve each). ``planes``: the views'
    local planes (:func:`estimate_normals`) when the caller keeps them between calls. ``cameras``: each
    view's camera centre ({W}, mm): a point seen at incidence theta is noisier by 1/cos(theta) (and biased by
    what the sensor's model misses, which grows with it), so pairs are weighted by their incidence and pairs
    beyond ``MAX_INCIDENCE_DEG`` for either view are not used: a view that overlaps the others only at
    grazing incidence is held by the prior, not slid along by its least reliable points."""
    n_views = len(views)
    T = [np.eye(4) for _ in range(n_views)]
    if n_views < 2:
        return ViewRefinement(T, 0.0, 0.0, [0] * n_views, list(range(n_views)))
    rng = np.random.default_rng(seed)
    nonempty = [v for v in views if len(v)]
    centre = np.vstack(nonempty).mean(axis=0) if nonempty else np.zeros(3)
    lever = max(float(np.linalg.norm(np.vstack(nonempty) - centre, axis=1).max()), 1.0) if nonempty else 1.0
    normals = planes if planes is not None else [estimate_normals(v) for v in views]
    sigma_r = np.broadcast_to(np.asarray(sigma_r_rad, dtype=np.float64), (n_views,))
    sigma_t = np.broadcast_to(np.asarray(sigma_t_mm, dtype=np.float64), (n_views,))
    # per view: three rotation weights (as mm at the lever arm), three translation weights
    prior_w = np.repeat(np.column_stack([1 / (sigma_r * lever) ** 2, 1 / sigma_t**2]), 3, axis=1).ravel()
    x = np.zeros((n_views, 6))
    rms: list[float] = []
    overlaps = [0] * n_views
    last_gaps: list[Array] = []
    for radius in radii_mm:
        moved = [transform_points(Ti, v) for Ti, v in zip(T, views, strict=True)]
        moved_n = [(Ti[:3, :3] @ lp.normal.T).T for Ti, lp in zip(T, normals, strict=True)]
        moved_c = [transform_points(Ti, lp.centroid) for Ti, lp in zip(T, normals, strict=True)]
        eyes = None if cameras is None else [transform_points(Ti, e) for Ti, e in zip(T, cameras)]
        trees = [cKDTree(m) if len(m) else None for m in moved]
        boxes = [(m.min(0), m.max(0)) if len(m) else (np.zeros(3), np.zeros(3)) for m in moved]
        H = np.zeros((6 * n_views, 6 * n_views))
        g = np.zeros(6 * n_views)
        gaps_all: list[Array] = []
        pairs: list[tuple[int, int, Array, Array]] = []
        overlaps = [0] * n_views
        used = np.zeros(n_views)  # pairs (incidence-weighted) that hold each view, as source or target
        for i in range(n_views):
            for j in range(n_views):
                tree = trees[j]
                if i == j or tree is None or not len(moved[i]):
                    continue
                if not _boxes_overlap(boxes[i], boxes[j], radius):
                    continue
                src = _candidates(moved[i], normals[i].ok, boxes[j], radius, rng)
                d, nearest = tree.query(moved[i][src], distance_upper_bound=radius)
                hit = np.isfinite(d)
                src, k = src[hit], np.asarray(nearest)[hit]
                if len(src) == 0:
                    continue
                nj = moved_n[j][k]
                facing = np.abs(np.einsum("ij,ij->i", moved_n[i][src], nj)) > SAME_NORMAL_COS
                good = normals[j].ok[k] & facing
                src, k, nj = src[good], k[good], nj[good]
                if len(src) < MIN_PAIRS:
                    continue
                if len(src) > MAX_PAIRS_PER_OVERLAP:
                    pick = rng.choice(len(src), MAX_PAIRS_PER_OVERLAP, replace=False)
                    src, k, nj = src[pick], k[pick], nj[pick]
                p, q = moved[i][src], moved_c[j][k]
                r = np.einsum("ij,ij->i", p - q, nj)
                scale = 1.4826 * np.median(np.abs(r - np.median(r)))
                inlier = np.abs(r - np.median(r)) <= max(3 * scale, 2 * noise_mm)
                p, q, nj, r = p[inlier], q[inlier], nj[inlier], r[inlier]
                w_row = np.ones(len(r))
                if eyes is not None:
                    cos_i, cos_j = incidence_cos(p, nj, eyes[i]), incidence_cos(q, nj, eyes[j])
                    seen = np.minimum(cos_i, cos_j) >= MIN_INCIDENCE_COS
                    p, q, nj, r = p[seen], q[seen], nj[seen], r[seen]
                    w_row = 2.0 / (1.0 / cos_i[seen] ** 2 + 1.0 / cos_j[seen] ** 2)
                if len(r) < MIN_PAIRS:
                    continue
                overlaps[i] += 1
                gaps_all.append(r)
                used[i] += w_row.sum()
                used[j] += w_row.sum()
                # a gap holds two points' noise; each unordered pair is seen twice (i->j, j->i): half weight.
                # The pairs of one overlap are not independent (a view's calibration residual is smooth over
                # it, estimated normals share neighbours): together they count as EFFECTIVE_PAIRS, or the
                # noise in weakly constrained directions (a slide along a gentle curve) outweighs the prior
                w = 0.5 / (2 * noise_mm**2) * min(1.0, EFFECTIVE_PAIRS / len(r))
                # about the pair's midpoint, so that one motion of both views changes no gap (the gauge is
                # the prior's alone)
                Ji = np.column_stack([np.cross((p + q) / 2 - centre, nj) / lever, nj])
                Ji = Ji @ _observable(Ji)
                si, sj = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
                Wi = Ji * (w * w_row)[:, None]
                H[si, si] += Wi.T @ Ji
                H[sj, sj] += Wi.T @ Ji
                H[si, sj] -= Wi.T @ Ji
                H[sj, si] -= Wi.T @ Ji
                g[si] += Wi.T @ r
                g[sj] -= Wi.T @ r
                pairs.append((i, j, Ji, r))
        rms.append(float(np.sqrt(np.mean(np.concatenate(gaps_all) ** 2))) if gaps_all else 0.0)
        # a view that too few good pairs hold (it overlaps the others only at grazing incidence, or hardly at
        # all) stays at its kinematic pose: a few biased pairs would slide it where nothing checks it
        information = H.copy()
        held = used < MIN_VIEW_PAIRS
        for v in np.flatnonzero(held):
            H[6 * v : 6 * v + 6, 6 * v : 6 * v + 6] += np.eye(6) * 1e12
        # prior on the total correction x + dx: the solve is for the step dx
        H += np.diag(prior_w)
        g += prior_w * x.ravel()
        step = -np.linalg.solve(H, g).reshape(n_views, 6)
        x += step
        last_gaps = [r + Ji @ (step[i] - step[j]) for i, j, Ji, r in pairs]
        T = [_apply(xi, centre, lever) for xi in x]
    # the gaps of the last matching moved by the last step (linearised): what the corrections leave
    after = float(np.sqrt(np.mean(np.concatenate(last_gaps) ** 2))) if last_gaps else 0.0
    unregistered = [i for i in range(n_views) if held[i]] if radii_mm else list(range(n_views))
    return ViewRefinement(
        T, rms[0], after, overlaps, unregistered, information if radii_mm else None, centre, lever
    )
