"""The steps of the closed loop (sections 3.2-3.3): evaluate (shadow map IS, reflection map IR, accuracy map
IA and where the points' uncertainty misses its target, IU; cost Q of eq 3.22) and add viewpoints V_k with
g_kS (holes and shadows: cluster, box, place) and g_kR
(glare: rotate the sensor by beta > theta/2 about the spot, eqs 3.24-3.26). The controller runs the loop
(measure, evaluate, replan until Q is under the set point or the view budget is spent) through the inspection
job. Every decision is appended to the plan's log with its reason.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cell.geometry import Pose, incidence_cos, make_pose
from cell.planning.clustering import cluster_points
from cell.planning.coverage import coverage_fraction, covered_by_points
from cell.planning.measured import DefectRegion, MeasuredView
from cell.planning.planner import Plan, fill_holes
from cell.planning.viewpoints import Viewpoint

Array = NDArray[np.float64]
SAME_POSE_MM, SAME_POSE_RAD = 10.0, np.deg2rad(3.0)


def cost_q(hole_area_mm2: float, distance_area_mm2: float, w: float) -> float:
    """Eq 3.22: Q = |w u + j v| (u: hole cost, v: distance cost, both mm^2)."""
    return float(abs(complex(w * hole_area_mm2, distance_area_mm2)))


MAP_LINK_MM = 0.5  # the maps compare a point with the nearest point of another view within this distance
Pairs = tuple[NDArray[np.integer], NDArray[np.integer]]
# the pairs of two views (positions in the maps' view list) within a link distance: the first view's points
# that have a neighbour in the second, and that neighbour's index, both ascending in the first view's order
PairsOf = Callable[[int, int, float], Pairs]
NO_PAIRS: Pairs = (np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp))


def nearest_within(points: Array, tree: cKDTree | None, link_mm: float) -> Pairs:
    """The indices of ``points`` (mm) with a point of ``tree`` within ``link_mm``, and that nearest point's
    index in the tree; only points in the tree's box grown by the link distance are looked up."""
    if tree is None or tree.n == 0 or not len(points):
        return NO_PAIRS
    inside = np.flatnonzero(
        np.all((points >= tree.mins - link_mm) & (points <= tree.maxes + link_mm), axis=1)
    )
    d, k = tree.query(points[inside], distance_upper_bound=link_mm)
    near = np.isfinite(d)
    return inside[near], np.asarray(k)[near]


def pairs_at(views: list[MeasuredView]) -> PairsOf:
    """The maps' pairs found at the views' points as given (a KD-tree of each view's points, built once and
    used by both maps): what the maps use when the caller has no pairs of its own (:func:`evaluate`)."""
    trees = view_trees(views)
    return lambda a, b, link_mm: nearest_within(views[a].points_W, trees[b], link_mm)


class PairCache:
    """The maps' pairs of two views by the views' ids (:func:`nearest_within` of the first view's points in
    the second's tree, found at the points the views were first given: the inspection's evaluation points at
    their kinematic poses), kept while views are added: they depend on the two views alone, so a view's
    decode worker can find them as it arrives and a resumed run finds the same when first asked."""

    def __init__(self) -> None:
        self._pairs: dict[tuple[int, int, float], Pairs] = {}
        self._lock = threading.Lock()

    def forget(self, view: int) -> None:
        """Drop the pairs of view ``view`` (it is measured again: its pairs are found anew)."""
        with self._lock:
            self._pairs = {k: v for k, v in self._pairs.items() if view not in k[:2]}

    def pairs(self, a: int, b: int, link_mm: float, points_a: Array, tree_b: cKDTree | None) -> Pairs:
        """The pairs of view ``a`` (points ``points_a``) in view ``b`` (``tree_b``), found once."""
        key = (a, b, link_mm)
        with self._lock:
            found = self._pairs.get(key)
        if found is None:
            src, dst = nearest_within(points_a, tree_b, link_mm)
            # int32 (the same indices): the pairs of all view pairs are kept
            small = len(points_a) < 2**31 and (tree_b is None or tree_b.n < 2**31)
            found = (src.astype(np.int32), dst.astype(np.int32)) if small else (src, dst)
            with self._lock:
                self._pairs[key] = found
        return found


def accuracy_map(
    views: list[MeasuredView],
    normals_at: Callable[[Array], Array],
    tol_mm: float,
    link_mm: float = MAP_LINK_MM,
    first_new: int = 1,
    max_incidence_deg: float = 90.0,
    pairs: PairsOf | None = None,
) -> Array:
    """IA (eq 3.9): points of a view that disagree along the surface normal by more than ``tol_mm`` with the
    nearest point (within ``link_mm``) of an earlier overlapping view. Pairs whose nominal normals differ by
    more than 10 deg (across an edge or a thin sheet) are not compared. Normals: the views' own when they
    carry them, else the nominal normal at the point; views that carry their points' deviations from the
    nominal are compared by those instead. Only views from index ``first_new`` on are compared (with every
    earlier one), so each iteration checks what it added.

    A pair is compared only where both cameras see the surface within ``max_incidence_deg`` of its nominal
    normal (the task constraint theta_th2 of eq 3.5): a view measures more than it was planned for, and its
    points beyond the constraint are the grazing ones the sensor is not qualified for. (Coverage and the merge
    still take them: coverage counts what was measured at all, and the merge weighs points by decode quality,
    not incidence.) The nominal normal is the one of the later view's point: its closest nominal triangle's
    when the view carries them (``MeasuredView.nominal_normals_W``, found with its deviations), else
    ``normals_at`` the point.

    ``pairs``: which points are each other's nearest (:data:`PairsOf`; default: found at the views' points,
    :func:`pairs_at`). The inspection pairs its views once, at their kinematic poses, as each view arrives,
    and compares the pairs at the refined ones (cell.inspection); everything else here (incidence, normals,
    deviations, the flagged points) is taken at the points as given."""
    min_cos = float(np.cos(np.deg2rad(max_incidence_deg)))  # used below 90 deg only
    out = []
    pairs = pairs_at(views) if pairs is None else pairs
    for j in range(max(1, first_new), len(views)):
        vj = views[j]
        pj = vj.points_W
        if len(pj) == 0:
            continue
        found = [(i, *pairs(j, i, link_mm)) for i in range(j) if len(views[i].points_W)]
        found = [(i, src, dst) for i, src, dst in found if len(src)]
        if max_incidence_deg < 90.0 and found:
            # the nominal normal of each of view j's paired points, once however many views it is paired in
            used = np.zeros(len(pj), dtype=bool)
            for _, src, _ in found:
                used[src] = True
            at = np.cumsum(used) - 1  # where a paired point's normal (and view j's incidence) is in n_used
            n_used = normals_at(pj[used]) if vj.nominal_normals_W is None else vj.nominal_normals_W[used]
            seen_j = incidence_cos(pj[used], n_used, vj.T_W_C[:3, 3]) >= min_cos  # once per point too
        for i, src, dst in found:
            vi = views[i]
            pi = vi.points_W
            if max_incidence_deg < 90.0:
                k = at[src]
                ahead = seen_j[k]  # view j's incidence first: view i's is found for the pairs it leaves
                src, dst, k = src[ahead], dst[ahead], k[ahead]
                seen = incidence_cos(pi[dst], n_used[k], vi.T_W_C[:3, 3]) >= min_cos
                src, dst = src[seen], dst[seen]
            if not len(src):
                continue
            dj, di = vj.deviation_mm, vi.deviation_mm
            if dj is not None and di is not None:
                # deviations from the nominal: robust on bends and sheet edges, where normals are not
                gap = np.abs(dj[src] - di[dst])
            else:
                nj = vj.normals_W[src] if vj.normals_W is not None else normals_at(pj[src])
                ni = vi.normals_W[dst] if vi.normals_W is not None else normals_at(pi[dst])
                same = np.einsum("ij,ij->i", nj, ni) > np.cos(np.deg2rad(10.0))
                gap = np.abs(np.einsum("ij,ij->i", pj[src] - pi[dst], nj))
                src, gap = src[same], gap[same]
            flagged = gap > tol_mm
            if flagged.any():  # where the views agree (most pairs) there is nothing to check
                out.append(_consistent(pj[src], flagged))
    return np.vstack(out) if out else np.zeros((0, 3))


def view_trees(views: list[MeasuredView]) -> list[cKDTree | None]:
    """A KD-tree of each view's points (None for a view without points), for the accuracy and uncertainty
    maps of one evaluation: built once, used by both."""
    return [cKDTree(v.points_W) if len(v.points_W) else None for v in views]


def uncertainty_map(
    views: list[MeasuredView],
    u_max_mm: float,
    link_mm: float = MAP_LINK_MM,
    pairs: PairsOf | None = None,
) -> Array:
    """IU: points where the views together measure with a standard uncertainty above ``u_max_mm`` (the
    accuracy target, U = k u at most a quarter of the tolerance band, over k). Each view's points carry
    their own u (decode and calibration: what more views can average); where several views measured a spot
    (within ``link_mm``) their u combine as independent measurements, 1/u^2 = sum 1/u_v^2 (summed in view
    order). Only areas count (:func:`_consistent`): a few uncertain points at a sheet edge are no reason for
    a view. ``pairs``: which points are each other's nearest, as for :func:`accuracy_map`."""
    carrying = [k for k, v in enumerate(views) if v.uncertainty_mm is not None and len(v.points_W)]
    if not carrying:
        return np.zeros((0, 3))
    pairs = pairs_at(views) if pairs is None else pairs
    starts = np.cumsum([0] + [len(views[c].points_W) for c in carrying])
    info = np.zeros(starts[-1])
    for c in carrying:
        u = np.asarray(views[c].uncertainty_mm, dtype=np.float64)
        w = 1.0 / np.square(np.where(np.isfinite(u), u, np.inf))  # view c's information per point (1/mm^2)
        for a, start in zip(carrying, starts, strict=False):
            if a == c:  # each of the view's own points is its own nearest (at 0 mm)
                info[start : start + len(w)] += w
                continue
            src, dst = pairs(a, c, link_mm)
            info[start + src] += w[dst]
    with np.errstate(divide="ignore"):
        flagged = 1.0 / np.sqrt(info) > u_max_mm
    if not flagged.any():  # the views' points stacked only for points to check
        return np.zeros((0, 3))
    return _consistent(np.vstack([views[c].points_W for c in carrying]), flagged)


def _consistent(
    points: Array, flagged: NDArray[np.bool_], radius_mm: float = 1.0, share: float = 0.5, min_points: int = 5
) -> Array:
    """The flagged points whose neighbourhood (``radius_mm``) is mostly flagged too: a real disagreement
    between two views covers an area, while isolated mixed pixels at sheet edges do not."""
    if not flagged.any():
        return np.zeros((0, 3))
    candidates = points[flagged]
    # the points that can be within the radius of a candidate: those in the candidates' box grown by it (and
    # a micrometre, so rounding cannot drop one); the counts are the same as in a tree of all the points
    reach = radius_mm + 1e-6
    lo, hi = candidates.min(axis=0) - reach, candidates.max(axis=0) + reach
    near = points[np.all((points >= lo) & (points <= hi), axis=1)]
    n_all = cKDTree(near).query_ball_point(candidates, radius_mm, return_length=True)
    n_flag = cKDTree(candidates).query_ball_point(candidates, radius_mm, return_length=True)
    return candidates[(n_flag >= min_points) & (n_flag >= share * n_all)]


def rotate_about(T: Pose, point: Array, axis: Array, angle: float) -> Pose:
    """Rigid rotation of pose T about the line through ``point`` along ``axis`` (world)."""
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    return make_pose(R, point - R @ point) @ T


class FeedbackPlanner:
    """g_k: defect maps -> new viewpoints, on top of an initial plan."""

    def __init__(self, plan: Plan):
        self.plan = plan
        self.log = plan.log
        s = plan.surface
        self.tree = cKDTree(s.points)
        self.st = plan.sensor.settings

    def normals_at(self, pts: Array) -> Array:
        return self.plan.surface.normals[self.tree.query(pts)[1]]

    def samples_near(self, pts: Array, radius: float) -> NDArray[np.int64]:
        if len(pts) == 0:
            return np.zeros(0, dtype=np.int64)
        hits = self.tree.query_ball_point(pts, radius)
        return np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))

    def g_kR(self, region: DefectRegion, T_W_C: Pose, name: str) -> Viewpoint | None:
        """Glare spot: rotate the sensor about the spot centre by beta = theta/2 + margin (eqs 3.24-3.26)
        in the plane of the view and incident rays, toward whichever side is reachable and predicted
        glare-free."""
        sensor, s = self.plan.sensor, self.plan.surface
        p = region.points_W.mean(axis=0)
        T_W_P = sensor.projector_pose(T_W_C)
        V = p - T_W_C[:3, 3]
        V /= np.linalg.norm(V)
        N = p - T_W_P[:3, 3]
        N /= np.linalg.norm(N)
        theta = float(np.arccos(np.clip(V @ N, -1, 1)))  # eq 3.24
        beta = theta / 2 + np.deg2rad(self.st.glare_margin_deg)  # eq 3.26
        axis = np.cross(V, N)
        idx = self.samples_near(region.points_W, 2.0)
        if len(idx) == 0 or np.linalg.norm(axis) < 1e-9:
            return None
        spot_mirror = sensor.mirror_angle(T_W_C, s.points[idx], s.normals[idx]).max()
        best = None
        for sign in (1.0, -1.0):
            T = rotate_about(T_W_C, p, axis, sign * beta)
            ok, why = self.plan.patch_planner.reach.check(T)
            if not ok:
                self.log.append({"event": "g_kR_side_rejected", "patch": name, "reason": why, "sign": sign})
                continue
            meas = sensor.measurable(T, s.points[idx], s.normals[idx], s.occluder)
            clear = sensor.mirror_angle(T, s.points[idx], s.normals[idx]) > spot_mirror
            frac = float((meas & clear).mean())
            if best is None or frac > best[1]:
                best = (T, frac, sign, idx[meas & clear])
        if best is None or best[1] == 0:
            self.log.append(
                {
                    "event": "g_kR_failed",
                    "patch": name,
                    "reason": "no rotation side is reachable and measures the spot",
                }
            )
            return None
        T, frac, sign, meas = best
        self.log.append(
            {
                "event": "viewpoint",
                "source": "g_kR",
                "patch": name,
                "reason": f"glare spot of {region.pixels} px: theta = {np.rad2deg(theta):.1f} deg, rotate "
                f"beta = {np.rad2deg(beta):.1f} deg > theta/2 ({'forward' if sign > 0 else 'backward'})",
                "spot_fraction": round(frac, 3),
            }
        )
        return Viewpoint(T, self.plan.patch_planner.reach.target(T), name, "g_kR", frac, meas)

    def propose(
        self,
        k: int,
        new_views: list[MeasuredView],
        covered: NDArray[np.bool_],
        ia: Array,
        iu: Array | None = None,
    ) -> list[Viewpoint]:
        s = self.plan.surface
        out: list[Viewpoint] = []
        glare_owned = np.zeros(len(s.points), dtype=bool)
        for vi, mv in enumerate(new_views):
            for ri, reg in enumerate(r for r in mv.defects if r.reason == "glare"):
                idx = self.samples_near(reg.points_W, 2.0)
                if len(idx) == 0 or covered[idx].mean() > 0.9:
                    continue  # another view already measured the spot
                glare_owned[idx] = True
                vp = self.g_kR(reg, mv.T_W_C, f"R{k}.{vi}.{ri}")
                if vp is not None:
                    out.append(vp)
        holes = np.flatnonzero(s.inspectable & ~covered & ~glare_owned)
        shadow_pts = [r.boundary_W for mv in new_views for r in mv.defects if r.reason == "shadow"]
        if shadow_pts and len(np.vstack(shadow_pts)):
            self.log.append(
                {
                    "event": "shadow_map",
                    "reason": "IS: boundary points of shadow regions",
                    "points": int(sum(len(p) for p in shadow_pts)),
                }
            )
        out += fill_holes(self.plan.patch_planner, holes, f"S{k}.", "g_kS", self.log)
        why = {
            "A": f"IA: overlapping views disagree by > {self.st.accuracy_tol_mm} mm; add a redundant view",
            "U": "IU: U = k u above a quarter of the tolerance band; add a view to average",
        }
        for tag, flagged in (("A", ia), ("U", np.zeros((0, 3)) if iu is None else iu)):
            if not len(flagged):
                continue
            lab = cluster_points(flagged, 5.0)
            for c in range(int(lab.max()) + 1):
                idx = self.samples_near(flagged[lab == c], 2.0)
                if s.area[idx].sum() >= self.st.min_patch_area_mm2:
                    event = "accuracy" if tag == "A" else "uncertainty"
                    self.log.append({"event": event, "patch": f"{tag}{k}.{c}", "reason": why[tag]})
                    out += self.plan.patch_planner.plan(idx, f"{tag}{k}.{c}", f"g_k{tag}")
        return out


def is_duplicate(T: Pose, existing: list[Pose]) -> bool:
    for E in existing:
        if np.linalg.norm(T[:3, 3] - E[:3, 3]) < SAME_POSE_MM:
            R = E[:3, :3].T @ T[:3, :3]
            if np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)) < SAME_POSE_RAD:
                return True
    return False


@dataclass
class Evaluation:
    """The evaluator Lambda (eq 3.17) for one iteration: what is covered, the cost Q and the accuracy map."""

    covered: NDArray[np.bool_]
    coverage: float
    u_mm2: float  # uncovered inspectable area (holes)
    v_mm2: float  # area where overlapping views disagree (IA)
    q: float
    setpoint: float
    ia: Array
    iu: Array = field(default_factory=lambda: np.zeros((0, 3)))
    iu_mm2: float = 0.0  # area where the uncertainty misses its target (IU); Q counts IA and IU together

    @property
    def qualified(self) -> bool:
        return self.q <= self.setpoint

    def to_json(self) -> dict[str, Any]:
        return {
            "qualified": self.qualified,
            "coverage": round(self.coverage, 5),
            "u_mm2": round(self.u_mm2, 1),
            "v_mm2": round(self.v_mm2, 1),
            "iu_mm2": round(self.iu_mm2, 1),
            "Q": round(self.q, 1),
            "setpoint": round(self.setpoint, 1),
        }


def evaluate(
    fb: FeedbackPlanner,
    views: list[MeasuredView],
    first_new: int,
    ia_before: Array,
    u_max_mm: float | None = None,
    covered: NDArray[np.bool_] | None = None,
    pairs: PairsOf | None = None,
) -> Evaluation:
    """Coverage, hole area u, accuracy map IA (views from ``first_new`` on against earlier ones, added to
    ``ia_before``) and its area v, given the target ``u_max_mm`` the uncertainty map IU
    (:func:`uncertainty_map`) and its area, and Q = |w u + j v'| against the set point, v' the area of IA and
    IU together. ``covered``: the samples the views' points cover, when the caller counted them already
    (:func:`covered_by_views`). ``pairs``: which points of two views are each other's nearest (the maps'
    :data:`PairsOf`; default: found at the views' points, once for both maps)."""
    st, s = fb.st, fb.plan.surface
    if covered is None:
        pts = np.vstack([v.points_W for v in views]) if views else np.zeros((0, 3))
        covered = covered_by_points(s, pts, st.point_density_per_mm2, st.coverage_radius_mm)
    u = float(s.area[s.inspectable & ~covered].sum())
    pairs = pairs_at(views) if pairs is None else pairs  # for both maps
    ia = np.vstack(
        [
            ia_before,
            accuracy_map(
                views,
                fb.normals_at,
                st.accuracy_tol_mm,
                first_new=first_new,
                max_incidence_deg=st.theta_camera_deg,
                pairs=pairs,
            ),
        ]
    )
    iu = np.zeros((0, 3)) if u_max_mm is None else uncertainty_map(views, u_max_mm, pairs=pairs)
    v_area = float(s.area[fb.samples_near(ia, 1.0)].sum()) if len(ia) else 0.0
    iu_area = float(s.area[fb.samples_near(iu, 1.0)].sum()) if len(iu) else 0.0
    flagged = np.vstack([ia, iu])
    either = float(s.area[fb.samples_near(flagged, 1.0)].sum()) if len(flagged) else 0.0
    q = cost_q(u, either, st.hole_weight)  # the distance cost: where views disagree or u misses its target
    return Evaluation(
        covered,
        coverage_fraction(s, covered),
        u,
        v_area,
        q,
        st.q_setpoint_fraction * s.inspectable_area_mm2,
        ia,
        iu,
        iu_area,
    )


def select_new(fb: FeedbackPlanner, proposed: list[Viewpoint], done: list[Pose]) -> list[Viewpoint]:
    """The proposed viewpoints that are not a pose already in the run (measured, or skipped because no clear
    path reached it) nor proposed twice, within the view budget (logged)."""
    pending: list[Viewpoint] = []
    for vp in proposed:
        if is_duplicate(vp.T_W_C, done + [p.T_W_C for p in pending]):
            fb.log.append(
                {
                    "event": "duplicate",
                    "patch": vp.patch,
                    "reason": "an equal pose is already in the run (measured, or skipped as unreachable)",
                }
            )
            continue
        if len(done) + len(pending) >= fb.st.view_budget:
            fb.log.append({"event": "budget", "patch": vp.patch, "reason": "view budget spent"})
            break
        pending.append(vp)
    return pending
