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

import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cell.geometry import (
    Pose,
    bounding_box,
    incidence_cos,
    invert,
    make_pose,
    transform_points,
    transform_vectors,
)

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
    # the corrections x_i themselves, (n, 6), as the last solve left them (None when nothing was solved)
    x: Array | None = None
    # (n, n) the incidence-weighted pairs of the last matching between each two views (both ways, held views'
    # too): what decides which views are held (:func:`_held_views`)
    support: Array | None = None
    # how many gaps the rms before and after are over (so that a view added later can join them)
    gaps: tuple[int, int] = (0, 0)
    # per ordered view pair (i, j) of the last matching, its gaps e after the corrections (linearised) as
    # sum e^2 (mm^2), J^T e and J^T J of its rows J (d e / d(x_i - x_j)): what they become as views move on
    moments: list[tuple[int, int, float, Array, Array]] = field(default_factory=list)
    # the prior's weights on x, (6n,) (1 / sigma^2, the rotation's at the lever arm)
    prior_w: Array | None = None

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
    _, idx = cKDTree(points).query(points, k=k, workers=-1)
    centroid = points[idx].mean(axis=1)
    nb = points[idx] - centroid[:, None, :]
    cov = np.einsum("nki,nkj->nij", nb, nb) / k
    w, v = np.linalg.eigh(cov)
    # the normals copied out of the (n, 3, 3) eigenvectors: a view of them kept all nine per point alive with
    # the view (72 bytes a point instead of 24, in every completed view the job holds)
    return LocalPlanes(centroid, np.ascontiguousarray(v[:, :, 0]), w[:, 0] < 0.1 * np.maximum(w[:, 1], 1e-12))


def _observable(J: Array, ratio: float = 1e-4) -> Array:
    """Projector onto the motions an overlap observes. On a plane a slide along it changes no gap, yet the
    normals' estimation noise gives it a small, spurious information that would couple the overlap's normal
    offset into a slide; directions whose information is under ``ratio`` of the strongest are left to the
    prior (a truncated eigen-decomposition of J^T J)."""
    lam, U = np.linalg.eigh(J.T @ J)
    Uk = U[:, lam >= ratio * lam[-1]]
    return Uk @ Uk.T


def _boxes_overlap(a: tuple[Array, Array], b: tuple[Array, Array], margin: float) -> bool:
    """Whether two (min, max) boxes overlap when grown by ``margin``."""
    return bool(np.all(a[0] - margin <= b[1]) and np.all(b[0] - margin <= a[1]))


def _apply(x: NDArray[np.float64], centre: Array, lever_mm: float) -> Pose:
    """The rigid motion of a linearised correction (rotation vector * lever, translation) about ``centre``."""
    R = Rotation.from_rotvec(x[:3] / lever_mm).as_matrix()
    return make_pose(R, centre + x[3:] - R @ centre)


POOL_SLACK_MM = 1.0  # a view's candidate pool in another's box reaches this far beyond the first radius


@dataclass(frozen=True)
class _Side:
    """One view as the matching sees it: its points and local planes in its own frame, their KD-tree, its
    camera centre (or None), bounding box and id (what seeds the random draws of its pairs)."""

    points: Array
    planes: LocalPlanes
    tree: cKDTree | None
    camera: Array | None
    box: tuple[Array, Array]
    id: int


@dataclass(frozen=True)
class PairMatch:
    """One ordered overlap's matched pairs at given poses, all moved: the source points ``p``, the target's
    local-plane centroids ``q`` and normals ``n``, the point-to-plane gaps ``r`` (mm), incidence weights."""

    p: Array
    q: Array
    n: Array
    r: Array
    w: Array


# the candidates of a pool the cache keeps: a matching reads its pool in chunks of MAX_PAIRS_PER_OVERLAP // 2
# until twice MAX_PAIRS_PER_OVERLAP were looked up inside the target's box (the demo pillar's read at most
# 6000), while a pool holds all of the source's trusted points in the box (median 31k, up to 114k): the pools
# of all view pairs are kept, so the rest is drawn again when a matching reads past these
POOL_KEPT = 4 * MAX_PAIRS_PER_OVERLAP


class _Pool:
    """A pair's candidate pool (indices of the source's trusted ``points`` inside the box ``lo``-``hi``, in
    the random order seeded by ``seed``) as :class:`OverlapCache` keeps it: its first :data:`POOL_KEPT`
    indices (int32), the whole pool drawn again, the same, when a slice reaches past them."""

    def __init__(self, points: Array, ok: NDArray[np.bool_], lo: Array, hi: Array, seed: tuple[int, ...]):
        self._points, self._ok, self._lo, self._hi, self._seed = points, ok, lo, hi, seed
        whole = self._whole()
        self._size = len(whole)
        self._head = whole[:POOL_KEPT].copy()

    def _whole(self) -> NDArray[np.integer]:
        inside = np.all((self._points >= self._lo) & (self._points <= self._hi), axis=1)
        found = np.random.default_rng(list(self._seed)).permutation(np.flatnonzero(self._ok & inside))
        return found.astype(np.int32) if len(self._points) < 2**31 else found

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, part: slice) -> NDArray[np.integer]:
        stop = (
            self._size if part.stop is None else min(part.stop, self._size)
        )  # a slice past the end: its end
        return self._head[part] if stop <= len(self._head) else self._whole()[part]


class OverlapCache:
    """What the refinement finds between two views at their kinematic poses (no correction yet): each ordered
    pair's candidate pool (the source's trusted points in the target's box, grown by the first match radius
    and :data:`POOL_SLACK_MM`, in a random order of the pair's own) and its first matching, and each view's
    bounding box. They depend on the views alone, so they hold while views are added, and a view's decode
    worker can make them as it arrives (:func:`prepare_overlaps`)."""

    def __init__(self) -> None:
        self._pools: dict[tuple[int, int, float, int], _Pool] = {}
        self._first: dict[tuple[Any, ...], PairMatch | None] = {}
        self._boxes: dict[int, tuple[Array, Array]] = {}
        self._lock = threading.Lock()

    def forget(self, view: int) -> None:
        """Drop what the cache holds of view ``view`` (it is measured again: its overlaps are made anew)."""
        with self._lock:
            self._pools = {k: v for k, v in self._pools.items() if view not in k[:2]}
            self._first = {k: v for k, v in self._first.items() if view not in k[:2]}
            self._boxes.pop(view, None)

    def box(self, view: int, points: Array) -> tuple[Array, Array]:
        """The bounding box (min, max) of view ``view``'s ``points`` (zeros when it has none), found once."""
        with self._lock:
            found = self._boxes.get(view)
        if found is None:
            found = bounding_box(points) if len(points) else (np.zeros(3), np.zeros(3))
            with self._lock:
                self._boxes[view] = found
        return found

    def pool(self, a: _Side, b: _Side, radius_mm: float, seed: int) -> _Pool:
        key = (a.id, b.id, radius_mm, seed)
        with self._lock:
            found = self._pools.get(key)
        if found is None:
            lo, hi = b.box[0] - radius_mm - POOL_SLACK_MM, b.box[1] + radius_mm + POOL_SLACK_MM
            found = _Pool(a.points, a.planes.ok, lo, hi, (seed, a.id, b.id))
            with self._lock:
                self._pools[key] = found
        return found

    def first(self, key: tuple[Any, ...]) -> tuple[bool, PairMatch | None]:
        with self._lock:
            return (key in self._first), self._first.get(key)

    def keep_first(self, key: tuple[Any, ...], match: PairMatch | None) -> None:
        with self._lock:
            self._first[key] = match


def _sides(
    views: list[Array],
    planes: list[LocalPlanes],
    cameras: list[Array] | None,
    trees: list[cKDTree | None] | None,
    ids: list[int] | None,
    cache: OverlapCache,
) -> list[_Side]:
    return [
        _Side(
            v,
            lp,
            (trees[k] if trees is not None else (cKDTree(v) if len(v) else None)),
            None if cameras is None else np.asarray(cameras[k], dtype=np.float64),
            cache.box(k if ids is None else int(ids[k]), v),
            k if ids is None else int(ids[k]),
        )
        for k, (v, lp) in enumerate(zip(views, planes, strict=True))
    ]


def _match(
    a: _Side,
    b: _Side,
    T_a: Pose,
    T_b: Pose,
    box_b: tuple[Array, Array],
    radius: float,
    pool: _Pool,
    noise_mm: float,
) -> PairMatch | None:
    """The matched pairs of source ``a`` against target ``b`` with the views moved by ``T_a``, ``T_b``:
    ``a``'s pool points (in the pool's random order) inside ``b``'s moved box ``box_b`` grown by ``radius``
    are looked up in ``b``'s tree within ``radius`` (the query moved into ``b``'s own frame) and kept where
    both local planes face alike and ``b``'s is trusted, until :data:`MAX_PAIRS_PER_OVERLAP` are found or
    twice that many were looked up (a random sample of the overlap either way); robust outliers and grazing
    pairs are dropped; None when fewer than :data:`MIN_PAIRS` remain."""
    if b.tree is None or not len(pool):
        return None
    to_b = invert(T_b)
    chunk_size = MAX_PAIRS_PER_OVERLAP // 2
    ks, ps, ns, looked_up, found = [], [], [], 0, 0
    for start in range(0, len(pool), chunk_size):  # the pool is in random order: its first points will do
        src = pool[start : start + chunk_size]
        cand = transform_points(T_a, a.points[src])
        inside = np.all((cand >= box_b[0] - radius) & (cand <= box_b[1] + radius), axis=1)
        src, cand = src[inside], cand[inside]
        if not len(src):
            continue
        looked_up += len(src)
        d, nearest = b.tree.query(transform_points(to_b, cand), distance_upper_bound=radius)
        hit = np.isfinite(d)
        src, k, cand = src[hit], np.asarray(nearest)[hit], cand[hit]
        nj = transform_vectors(T_b, b.planes.normal[k])
        ni = transform_vectors(T_a, a.planes.normal[src])
        good = b.planes.ok[k] & (np.abs(np.einsum("ij,ij->i", ni, nj)) > SAME_NORMAL_COS)
        ks.append(k[good])
        ps.append(cand[good])
        ns.append(nj[good])
        found += int(good.sum())
        if found >= MAX_PAIRS_PER_OVERLAP or looked_up >= 2 * MAX_PAIRS_PER_OVERLAP:
            break
    if found < MIN_PAIRS:
        return None
    k = np.concatenate(ks)[:MAX_PAIRS_PER_OVERLAP]
    p = np.concatenate(ps)[:MAX_PAIRS_PER_OVERLAP]
    nj = np.concatenate(ns)[:MAX_PAIRS_PER_OVERLAP]
    q = transform_points(T_b, b.planes.centroid[k])
    r = np.einsum("ij,ij->i", p - q, nj)
    spread = np.abs(r - np.median(r))  # the median once
    scale = 1.4826 * np.median(spread)
    inlier = spread <= max(3 * scale, 2 * noise_mm)
    p, q, nj, r = p[inlier], q[inlier], nj[inlier], r[inlier]
    w_row = np.ones(len(r))
    if a.camera is not None and b.camera is not None:
        cos_i = incidence_cos(p, nj, transform_points(T_a, a.camera))
        cos_j = incidence_cos(q, nj, transform_points(T_b, b.camera))
        seen = np.minimum(cos_i, cos_j) >= MIN_INCIDENCE_COS
        p, q, nj, r = p[seen], q[seen], nj[seen], r[seen]
        w_row = 2.0 / (1.0 / cos_i[seen] ** 2 + 1.0 / cos_j[seen] ** 2)
    if len(r) < MIN_PAIRS:
        return None
    return PairMatch(p, q, nj, r, w_row)


def _first_key(a: _Side, b: _Side, radius: float, noise_mm: float, seed: int) -> tuple[Any, ...]:
    return (a.id, b.id, radius, noise_mm, seed, a.camera is not None and b.camera is not None)


def _first_match(
    a: _Side, b: _Side, radius: float, noise_mm: float, seed: int, cache: OverlapCache
) -> PairMatch | None:
    """The pair's matching at the kinematic poses (no correction), from ``cache`` or made and kept there."""
    key = _first_key(a, b, radius, noise_mm, seed)
    known, found = cache.first(key)
    if known:
        return found
    eye = np.eye(4)
    found = _match(a, b, eye, eye, b.box, radius, cache.pool(a, b, radius, seed), noise_mm)
    cache.keep_first(key, found)
    return found


def prepare_overlaps(
    cache: OverlapCache,
    views: list[Array],
    planes: list[LocalPlanes],
    cameras: list[Array] | None,
    trees: list[cKDTree | None],
    ids: list[int],
    new: int,
    noise_mm: float = 0.05,
    radius_mm: float = 2.0,
    seed: int = 0,
) -> None:
    """Make the first matching (at the kinematic poses, :func:`refine_views`' first radius) of view ``new``
    (a position in the lists) with every other view, both ways, into ``cache``: what a refinement over these
    views does first, done as the view arrives."""
    sides = _sides(views, planes, cameras, trees, ids, cache)
    for other in range(len(sides)):
        if other == new:
            continue
        for a, b in ((sides[new], sides[other]), (sides[other], sides[new])):
            if len(a.points) and _boxes_overlap(a.box, b.box, radius_mm):
                _first_match(a, b, radius_mm, noise_mm, seed, cache)


def refine_views(
    views: list[Array],
    sigma_t_mm: float | Array,
    sigma_r_rad: float | Array,
    noise_mm: float = 0.05,
    radii_mm: tuple[float, ...] = (2.0, 1.0, 0.6),
    seed: int = 0,
    planes: list[LocalPlanes] | None = None,
    cameras: list[Array] | None = None,
    trees: list[cKDTree | None] | None = None,
    ids: list[int] | None = None,
    cache: OverlapCache | None = None,
) -> ViewRefinement:
    """Corrections for ``views`` (points in {W}, mm; one array per view) under the prior (``sigma_t_mm``,
    ``sigma_r_rad``: 1-sigma translation and rotation of a view's pose, one for all or one per view) with
    point gaps of ``noise_mm`` noise, matching within each of ``radii_mm`` in turn (one linearised solve
    each). ``planes``: the views' local planes (:func:`estimate_normals`) when the caller keeps them between
    calls. ``cameras``: each view's camera centre ({W}, mm): a point seen at incidence theta is noisier by
    1/cos(theta) (and biased by what the sensor's model misses, which grows with it), so pairs are weighted
    by their incidence and pairs beyond ``MAX_INCIDENCE_DEG`` for either view are not used: a view that
    overlaps the others only at grazing incidence is held by the prior, not slid along by its least reliable
    points. ``trees``: KD-trees of the views as given (built here when None); matches are looked up with the
    query points moved into the other view's own frame, so no tree is rebuilt when a correction moves a view.
    Each ordered pair samples its overlap in a random order of its own, seeded by ``seed`` and the two views'
    ``ids`` (default: their positions), so a pair's matching depends on the two views alone and the pairs
    are matched on two threads; ``cache`` keeps the pairs' candidate pools and first matching between calls
    (:class:`OverlapCache`)."""
    n_views = len(views)
    T = [np.eye(4) for _ in range(n_views)]
    if n_views < 2:
        return ViewRefinement(T, 0.0, 0.0, [0] * n_views, list(range(n_views)))
    nonempty = [v for v in views if len(v)]
    every = np.vstack(nonempty) if nonempty else np.zeros((0, 3))  # stacked once: centre and lever arm
    centre = every.mean(axis=0) if nonempty else np.zeros(3)
    lever = max(float(np.linalg.norm(every - centre, axis=1).max()), 1.0) if nonempty else 1.0
    del every
    normals = planes if planes is not None else [estimate_normals(v) for v in views]
    cache = cache if cache is not None else OverlapCache()
    sides = _sides(views, normals, cameras, trees, ids, cache)
    sigma_r = np.broadcast_to(np.asarray(sigma_r_rad, dtype=np.float64), (n_views,))
    sigma_t = np.broadcast_to(np.asarray(sigma_t_mm, dtype=np.float64), (n_views,))
    # per view: three rotation weights (as mm at the lever arm), three translation weights
    prior_w = np.repeat(np.column_stack([1 / (sigma_r * lever) ** 2, 1 / sigma_t**2]), 3, axis=1).ravel()
    x = np.zeros((n_views, 6))
    rms: list[float] = []
    counted: list[int] = []  # the gaps each matching found
    support = np.zeros((n_views, n_views))
    overlaps = [0] * n_views
    last_gaps: list[Array] = []
    last_rows: list[tuple[int, int, Array]] = []
    held = np.zeros(n_views, dtype=bool)
    information: Array | None = None
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="refine") as pool:
        for it, radius in enumerate(radii_mm):
            boxes = [
                _moved_box(Ti, side.points, side.box) if it else side.box
                for Ti, side in zip(T, sides, strict=True)
            ]
            ordered = [
                (i, j)
                for i in range(n_views)
                for j in range(n_views)
                if i != j
                and len(views[i])
                and sides[j].tree is not None
                and _boxes_overlap(boxes[i], boxes[j], radius)
            ]

            matched = functools.partial(
                _pair_match, sides, it == 0, radius, T, boxes, cache, radii_mm[0], seed, noise_mm
            )
            matches = [
                (i, j, m)
                for (i, j), m in zip(ordered, pool.map(matched, ordered), strict=True)
                if m is not None
            ]
            overlaps = [0] * n_views
            for i, _, _ in matches:
                overlaps[i] += 1
            # a view that too few good pairs hold (it overlaps the others only at grazing incidence, or hardly
            # at all) stays at its kinematic pose: a few biased pairs would slide it where nothing checks it,
            # and they move no other view either (they would pin its neighbours to its kinematic pose with an
            # overlap's full weight: the pillar's view 11 pulled ten views by 66-147 um, docs/benchmarks.md).
            # The views' pose covariance (cell.analysis.uncertainty.posterior_covariance) leaves them out the
            # same way. Counted until no more views are held: a neighbour that passes MIN_VIEW_PAIRS only with
            # a held view's pairs would be registered on fewer
            support = _support(n_views, matches)
            held = _held_views(support)
            H = np.zeros((6 * n_views, 6 * n_views))
            g = np.zeros(6 * n_views)
            gaps_all: list[Array] = []
            pairs: list[tuple[int, int, Array, Array]] = []
            for i, j, match in matches:
                p, q, nj, r, w_row = match.p, match.q, match.n, match.r, match.w
                gaps_all.append(r)
                Ji = _pair_jacobian(p, q, nj, centre, lever)
                pairs.append((i, j, Ji, r))  # the gaps after the step, held views' too
                if held[i] or held[j]:
                    continue
                _add_pair(H, g, i, j, Ji, _pair_weight(len(r), noise_mm) * w_row, r)
            rms.append(float(np.sqrt(np.mean(np.concatenate(gaps_all) ** 2))) if gaps_all else 0.0)
            counted.append(sum(len(r) for r in gaps_all))
            information = H.copy()  # the overlaps' alone, for cell.analysis.uncertainty
            for v in np.flatnonzero(held):
                H[6 * v : 6 * v + 6, 6 * v : 6 * v + 6] += np.eye(6) * 1e12
            # prior on the total correction x + dx: the solve is for the step dx
            H += np.diag(prior_w)
            g += prior_w * x.ravel()
            step = -np.linalg.solve(H, g).reshape(n_views, 6)
            step[held] = -x[held]  # back at its kinematic pose, where an earlier (wider) matching moved it
            x += step
            last_gaps = [r + Ji @ (step[i] - step[j]) for i, j, Ji, r in pairs]
            last_rows = [(i, j, Ji) for i, j, Ji, _ in pairs]
            T = [_apply(xi, centre, lever) for xi in x]
    # the gaps of the last matching moved by the last step (linearised): what the corrections leave
    after = float(np.sqrt(np.mean(np.concatenate(last_gaps) ** 2))) if last_gaps else 0.0
    unregistered = [i for i in range(n_views) if held[i]] if radii_mm else list(range(n_views))
    return ViewRefinement(
        T,
        rms[0] if rms else 0.0,
        after,
        overlaps,
        unregistered,
        information if radii_mm else None,
        centre,
        lever,
        x.copy() if radii_mm else None,
        support,
        (counted[0], sum(len(r) for r in last_gaps)) if counted else (0, 0),
        [
            (i, j, float(e @ e), Ji.T @ e, Ji.T @ Ji)
            for (i, j, Ji), e in zip(last_rows, last_gaps, strict=True)
        ],
        prior_w,
    )


def refine_newest(
    older: ViewRefinement,
    views: list[Array],
    sigma_t_mm: float,
    sigma_r_rad: float,
    noise_mm: float = 0.05,
    radii_mm: tuple[float, ...] = (2.0, 1.0, 0.6),
    seed: int = 0,
    planes: list[LocalPlanes] | None = None,
    cameras: list[Array] | None = None,
    trees: list[cKDTree | None] | None = None,
    ids: list[int] | None = None,
    cache: OverlapCache | None = None,
) -> ViewRefinement | None:
    """The refinement of ``views`` made from ``older``, :func:`refine_views` of all but the newest (the last
    of them; its arguments as there, ``sigma_t_mm``, ``sigma_r_rad`` the newest view's prior), and the newest
    view's pairs alone: the others' pairs are not matched again. The same schedule as the joint solve: the
    newest view's first matching at the kinematic poses (its gaps moved by the others' corrections,
    linearised), then one at each later radius at the present corrections; each solves, about ``older``'s
    centre and lever, for the newest view's correction x_n = (omega * lever, tau) and the others' further
    motion D from ``older``'s x

        D^T A D  +  sum over the newest view's pairs with the registered others  w (r + J (x_n - x_j))^2
                 +  prior(x_n)

    where A (``older``'s information and prior) is what the others' pairs and priors say about D: ``older``
    is their minimum, so their objective grows as D^T A D about it (linearised at its last matching). The
    newest view is held at its kinematic pose when its pairs with the registered others are fewer than
    :data:`MIN_VIEW_PAIRS`, and then moves no other view; the others keep ``older``'s held set. The
    information holds ``older``'s and the newest view's pairs' of its last matching. None when ``older``
    solved nothing (fewer than two views) or when the newest view's pairs would change which views the joint
    solve of all holds (a held view released by them, or the newest view held or not only through one): the
    caller then solves jointly (:func:`refine_views`)."""
    if older.x is None or older.centre_mm is None or older.prior_w is None or not radii_mm:
        return None
    n_views, new = len(views), len(views) - 1
    centre, lever = older.centre_mm, older.lever_mm
    normals = planes if planes is not None else [estimate_normals(v) for v in views]
    cache = cache if cache is not None else OverlapCache()
    sides = _sides(views, normals, cameras, trees, ids, cache)
    held_old = np.zeros(n_views, dtype=bool)
    held_old[older.unregistered] = True
    # what the others' pairs and priors say about their further motion D (older's last solve, its normal
    # equations' matrix), the held views pinned
    A = np.zeros((6 * n_views, 6 * n_views))
    if older.information is not None:
        A[: 6 * new, : 6 * new] = older.information
    A[: 6 * new, : 6 * new] += np.diag(older.prior_w)
    pinned = np.repeat(held_old, 6)
    A[pinned, pinned] += 1e12
    prior_w = np.repeat([1 / (sigma_r_rad * lever) ** 2, 1 / sigma_t_mm**2], 3)
    x = np.vstack([older.x, np.zeros((1, 6))])  # the corrections: older's, and the newest view's
    D = np.zeros_like(x)  # the others' motion from older's (the newest view's row unused)
    T = [*older.T, np.eye(4)]
    before: list[Array] = []
    last: list[tuple[int, int, Array, Array]] = []  # the newest view's pairs: i, j, rows J, gaps after
    matches: list[tuple[int, int, PairMatch]] = []
    held_new = False
    boxes_old = [_moved_box(Ti, s.points, s.box) for Ti, s in zip(T[:new], sides[:new], strict=True)]
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="refine") as pool:
        for it, radius in enumerate(radii_mm):
            # at the first radius all views at their kinematic poses (the pairs' first matching), later at
            # the present corrections
            if it == 0:
                boxes = [s.box for s in sides]
            else:
                boxes_old = [
                    _moved_box(T[k], sides[k].points, sides[k].box) if D[k].any() else boxes_old[k]
                    for k in range(new)
                ]
                boxes = [*boxes_old, _moved_box(T[new], sides[new].points, sides[new].box)]
            ordered = [
                ij
                for j in range(new)
                for ij in ((new, j), (j, new))
                if len(views[ij[0]])
                and sides[ij[1]].tree is not None
                and _boxes_overlap(boxes[ij[0]], boxes[ij[1]], radius)
            ]

            matched = functools.partial(
                _pair_match, sides, it == 0, radius, T, boxes, cache, radii_mm[0], seed, noise_mm
            )
            matches = [
                (i, j, m)
                for (i, j), m in zip(ordered, pool.map(matched, ordered), strict=True)
                if m is not None
            ]
            # the corrections since the poses the pairs were matched at (all of them at the first matching)
            since = (x + D) if it == 0 else np.zeros_like(x)
            used = sum(m.w.sum() for i, j, m in matches if not held_old[j if i == new else i])
            held_new = bool(used < MIN_VIEW_PAIRS)
            H = A.copy()
            g = A @ D.ravel()
            sn = slice(6 * new, 6 * new + 6)
            H[sn, sn] += np.diag(prior_w) + (np.eye(6) * 1e12 if held_new else 0.0)
            g[sn] += prior_w * x[new]
            pairs: list[tuple[int, int, Array, Array]] = []
            for i, j, match in matches:
                p, q, nj, r, w_row = match.p, match.q, match.n, match.r, match.w
                if it == 0:
                    before.append(r)
                Ji = _pair_jacobian(p, q, nj, centre, lever)
                r = r + Ji @ (since[i] - since[j])  # the gaps at the present corrections (linearised)
                pairs.append((i, j, Ji, r))
                if held_new or held_old[j if i == new else i]:
                    continue
                _add_pair(H, g, i, j, Ji, _pair_weight(len(r), noise_mm) * w_row, r)
            step = -np.linalg.solve(H, g).reshape(n_views, 6)
            step[held_old] = 0.0
            if held_new:
                step[new] = -x[new]
            x[new] += step[new]
            D[:new] += step[:new]
            last = [(i, j, Ji, r + Ji @ (step[i] - step[j])) for i, j, Ji, r in pairs]
            T = [
                *(
                    older.T[k] if not D[k].any() else _apply(older.x[k] + D[k], centre, lever)
                    for k in range(new)
                ),
                _apply(x[new], centre, lever),
            ]
    support = np.zeros((n_views, n_views))
    support[:new, :new] = older.support
    support += _support(n_views, matches)
    if (_held_views(support) != np.append(held_old[:new], held_new)).any():
        return None
    information = np.zeros((6 * n_views, 6 * n_views))
    if older.information is not None:
        information[: 6 * new, : 6 * new] = older.information
    moments = []
    for i, j, b0, b1, B2 in older.moments:  # the others' gaps moved on by D
        d = D[i] - D[j]
        moments.append((i, j, b0 + 2 * float(b1 @ d) + float(d @ B2 @ d), b1 + B2 @ d, B2))
    for (i, j, Ji, e), (_, _, match) in zip(last, matches, strict=True):
        moments.append((i, j, float(e @ e), Ji.T @ e, Ji.T @ Ji))
        if held_new or held_old[j if i == new else i]:
            continue
        WJ = (Ji * (_pair_weight(len(e), noise_mm) * match.w)[:, None]).T @ Ji
        si, sj = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
        information[si, si] += WJ
        information[sj, sj] += WJ
        information[si, sj] -= WJ
        information[sj, si] -= WJ
    overlaps = [*older.overlaps, 0]
    for i, _, _ in matches:
        overlaps[i] += 1
    n_before = older.gaps[0] + sum(len(r) for r in before)
    n_after = older.gaps[1] + sum(len(e) for _, _, _, e in last)
    b2 = older.rms_before_mm**2 * older.gaps[0] + sum(float(r @ r) for r in before)
    a2 = sum(m[2] for m in moments)
    return ViewRefinement(
        T,
        float(np.sqrt(b2 / n_before)) if n_before else 0.0,
        float(np.sqrt(max(a2, 0.0) / n_after)) if n_after else 0.0,
        overlaps,
        sorted([*older.unregistered, new] if held_new else older.unregistered),
        information,
        centre,
        lever,
        x + D,
        support,
        (n_before, n_after),
        moments,
        np.append(older.prior_w, prior_w),
    )


def _support(n_views: int, matches: list[tuple[int, int, PairMatch]]) -> Array:
    """(n, n) the incidence-weighted pairs of ``matches`` (i, j, match) between each two views, both ways."""
    support = np.zeros((n_views, n_views))
    for i, j, match in matches:
        w = match.w.sum()
        support[i, j] += w
        support[j, i] += w
    return support


def _held_views(support: Array) -> NDArray[np.bool_]:
    """Which views too few good pairs hold (:data:`MIN_VIEW_PAIRS`) given ``support`` (:func:`_support`):
    counted until no more views are held, a view's pairs with held views not counting (a neighbour that
    passes MIN_VIEW_PAIRS only with a held view's pairs would be registered on fewer)."""
    held = np.zeros(len(support), dtype=bool)
    while True:
        used = support[:, ~held].sum(axis=1)  # pairs holding each view, as source or target
        now_held = held | (used < MIN_VIEW_PAIRS)  # only grows: at most n rounds
        if (now_held == held).all():
            return held
        held = now_held


def _pair_match(
    sides: list[_Side],
    first: bool,
    radius: float,
    poses: list[Pose],
    boxes: list[tuple[Array, Array]],
    cache: OverlapCache,
    pool_radius: float,
    seed: int,
    noise_mm: float,
    ij: tuple[int, int],
) -> PairMatch | None:
    """The ordered pair ``ij``'s matching within ``radius``: ``first``, at the kinematic poses (the pair's own
    business, kept in ``cache`` between calls), else at the present corrections ``poses`` from the pair's
    candidate pool (drawn at ``pool_radius``, the first radius)."""
    i, j = ij
    a, b = sides[i], sides[j]
    if first:
        return _first_match(a, b, radius, noise_mm, seed, cache)
    return _match(a, b, poses[i], poses[j], boxes[j], radius, cache.pool(a, b, pool_radius, seed), noise_mm)


def _pair_weight(n_gaps: int, noise_mm: float) -> float:
    """The weight of each of a pair's ``n_gaps`` gaps (1/mm^2, before its incidence weight). A gap holds two
    points' noise; each unordered pair is seen twice (i->j, j->i): half weight. The pairs of one overlap are
    not independent (a view's calibration residual is smooth over it, estimated normals share neighbours):
    together they count as EFFECTIVE_PAIRS, or the noise in weakly constrained directions (a slide along a
    gentle curve) outweighs the prior."""
    return 0.5 / (2 * noise_mm**2) * min(1.0, EFFECTIVE_PAIRS / n_gaps)


def _pair_jacobian(p: Array, q: Array, n: Array, centre: Array, lever: float) -> Array:
    """The gaps' derivative (K, 6) by a view's correction (omega * lever, tau) about ``centre``: about the
    pair's midpoints (p + q) / 2, so that one motion of both views changes no gap (the gauge is the prior's
    alone), along the target's normals ``n``; only its observable directions (:func:`_observable`)."""
    J = np.column_stack([np.cross((p + q) / 2 - centre, n) / lever, n])
    return J @ _observable(J)


def _add_pair(H: Array, g: Array, i: int, j: int, J: Array, w: Array, r: Array) -> None:
    """Add the pair (i, j)'s gaps ``r`` (weights ``w``, derivative ``J`` by x_i, -J by x_j) to the normal
    equations ``H`` dx = -``g`` of the stacked corrections, in place."""
    si, sj = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
    Wi = J * w[:, None]
    WJ = Wi.T @ J  # once for the four blocks
    H[si, si] += WJ
    H[sj, sj] += WJ
    H[si, sj] -= WJ
    H[sj, si] -= WJ
    g[si] += Wi.T @ r
    g[sj] -= Wi.T @ r


def _moved_box(T: Pose, points: Array, box: tuple[Array, Array]) -> tuple[Array, Array]:
    """The bounding box of ``points`` (their own box: ``box``) moved by the rigid motion ``T``. A turn R moves
    a point relative to the box's centre by at most |R - I| times its distance from it, so a point farther
    than twice that inside every face of ``box`` cannot be extreme once moved: only the points near a face
    are moved (a small correction's box from a few percent of the points; the same box)."""
    if not len(points):
        return np.zeros(3), np.zeros(3)
    lo, hi = box
    # how far the turn moves a point relative to the centre at most: |R - I| (its Frobenius norm, at least the
    # spectral one) times the half-diagonal
    reach = float(np.linalg.norm(T[:3, :3] - np.eye(3)) * np.linalg.norm(hi - lo) / 2)
    margin = 2.0 * reach + 1e-6  # and a nanometre for the rounding of the moved coordinates
    near = np.flatnonzero(np.any((points >= hi - margin) | (points <= lo + margin), axis=1))
    moved = transform_points(T, points[near])
    return moved.min(0), moved.max(0)
