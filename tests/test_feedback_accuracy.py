"""The accuracy map IA (eq 3.9) against planted truth: views of a plane z = 0 whose points are offset by known
amounts, seen by cameras at known incidence."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.geometry import make_pose, transform_points
from cell.planning.feedback import PairCache, PairsOf, accuracy_map, uncertainty_map
from cell.planning.measured import MeasuredView

UP = np.array([0.0, 0.0, 1.0])


def normals_up(points: np.ndarray) -> np.ndarray:
    return np.tile(UP, (len(points), 1))


def view_of_plane(
    offset_mm: float, incidence_deg: float = 0.0, seed: int = 0, with_deviations: bool = True
) -> MeasuredView:
    """A 40 x 40 mm patch of the plane z = 0 measured ``offset_mm`` too high with 0.01 mm noise, by a camera
    400 mm away whose line of sight meets the plane's normal at ``incidence_deg``."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-20.0, 20.0, (20000, 2))
    z = offset_mm + rng.normal(0.0, 0.01, len(xy))
    points = np.column_stack([xy, z])
    a = np.deg2rad(incidence_deg)
    eye = 400.0 * np.array([np.sin(a), 0.0, np.cos(a)])
    T_W_C = make_pose(np.eye(3), eye)  # only the camera centre matters to the map
    return MeasuredView(T_W_C, points, deviation_mm=z if with_deviations else None)


def ia_area_fraction(views: list[MeasuredView], **kw: float) -> float:
    """Flagged points as a share of one view's points."""
    return len(accuracy_map(views, normals_up, 0.1, **kw)) / len(views[0].points_W)


@pytest.mark.parametrize("with_deviations", [True, False])
def test_views_that_agree_are_not_flagged_and_views_that_differ_are(with_deviations: bool) -> None:
    agree = [
        view_of_plane(0.0, seed=0, with_deviations=with_deviations),
        view_of_plane(0.03, seed=1, with_deviations=with_deviations),
    ]
    assert ia_area_fraction(agree) == 0.0
    differ = [
        view_of_plane(0.0, seed=0, with_deviations=with_deviations),
        view_of_plane(0.2, seed=1, with_deviations=with_deviations),
    ]
    assert ia_area_fraction(differ) > 0.5  # the whole overlap (the link radius trims a few points)


def test_a_pair_beyond_the_incidence_limit_is_not_compared() -> None:
    grazing = [view_of_plane(0.0, seed=0), view_of_plane(0.2, incidence_deg=72.0, seed=1)]
    assert ia_area_fraction(grazing, max_incidence_deg=90.0) > 0.5
    assert ia_area_fraction(grazing, max_incidence_deg=60.0) == 0.0
    earlier_grazing = [view_of_plane(0.0, incidence_deg=72.0, seed=0), view_of_plane(0.2, seed=1)]
    assert ia_area_fraction(earlier_grazing, max_incidence_deg=60.0) == 0.0
    within = [view_of_plane(0.0, seed=0), view_of_plane(0.2, incidence_deg=45.0, seed=1)]
    assert ia_area_fraction(within, max_incidence_deg=60.0) > 0.5


def test_views_apart_along_the_normal_by_less_than_the_link_are_compared() -> None:
    """Two views of a horizontal plane 0.2 mm apart have bounding boxes that do not overlap in z: the box test
    must allow the link distance, or they are never compared."""
    apart = [view_of_plane(0.0, seed=0), view_of_plane(0.3, seed=1)]
    assert apart[0].points_W[:, 2].max() < apart[1].points_W[:, 2].min()
    assert ia_area_fraction(apart) > 0.5


def test_uncertainty_map_combines_overlapping_views() -> None:
    """IU: two patches of the plane, each point measured with u = 4 um, overlap over x in [0, 20] mm. Where
    both measured, u combines to 4 / sqrt(2) = 2.83 um, under the 3 um target; where one did, 4 um is over
    it: the flagged points are the single-view strips, all of them (but their outermost 1 mm, where a
    neighbourhood reaches into the overlap)."""
    rng = np.random.default_rng(1)

    def patch(x0: float) -> MeasuredView:
        xy = np.column_stack([rng.uniform(x0, x0 + 40.0, 20000), rng.uniform(-20.0, 20.0, 20000)])
        points = np.column_stack([xy, np.zeros(len(xy))])
        return MeasuredView(
            make_pose(np.eye(3), [0.0, 0.0, 400.0]), points, uncertainty_mm=np.full(20000, 0.004)
        )

    a, b = patch(-20.0), patch(0.0)
    flagged = uncertainty_map([a, b], 0.003)
    x = flagged[:, 0]
    assert np.all((x < 0.5) | (x > 19.5))  # none inside the overlap (the link distance at its edges)
    single = np.count_nonzero(a.points_W[:, 0] < -1.0) + np.count_nonzero(b.points_W[:, 0] > 21.0)
    assert len(flagged) >= single


# ---------------------------------------------------------------- pairs found once, at the kinematic points
LINK = 0.5
COS60 = float(np.cos(np.deg2rad(60.0)))


def corrected_views(shift_mm: float, turn_rad: float) -> tuple[list[np.ndarray], list[MeasuredView]]:
    """Three overlapping 12 x 12 mm patches of the plane z = 0 (900 points each, 0.01 mm noise, u 3-6 um),
    their points as measured at the kinematic poses and the views after a known rigid correction each (a
    turn of ``turn_rad`` about a random axis through the origin, a shift of ``shift_mm``); view 2 measures a
    2.5 mm disc 0.15 mm high, view 1's camera is close and low, so its incidence crosses 60 deg."""
    rng = np.random.default_rng(7)
    kinematic, views = [], []
    for v, (x0, eye) in enumerate(zip((0.0, 6.0, 3.0), ((6, 6, 400), (28, 6, 10), (9, 6, 400)), strict=True)):
        xy = rng.uniform([x0, 0.0], [x0 + 12.0, 12.0], (900, 2))
        z = rng.normal(0.0, 0.01, len(xy)) + 0.15 * (v == 2) * (np.hypot(xy[:, 0] - 9, xy[:, 1] - 6) < 2.5)
        points = np.column_stack([xy, z])
        axis = rng.normal(size=3)
        direction = rng.normal(size=3)
        T = make_pose(
            Rotation.from_rotvec(axis / np.linalg.norm(axis) * turn_rad).as_matrix(),
            direction / np.linalg.norm(direction) * shift_mm,
        )
        moved = transform_points(T, points)
        u = rng.uniform(0.003, 0.006, len(points))
        kinematic.append(points)
        views.append(
            MeasuredView(T @ make_pose(np.eye(3), eye), moved, deviation_mm=moved[:, 2], uncertainty_mm=u)
        )
    return kinematic, views


def brute_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point of ``a`` with a point of ``b`` nearer than LINK, and the nearest one (all distances)."""
    d = cdist(a, b)
    k = d.argmin(axis=1)
    near = np.flatnonzero(d[np.arange(len(a)), k] < LINK)
    return near, k[near]


def brute_consistent(points: np.ndarray, flagged: np.ndarray) -> np.ndarray:
    """The flagged points with at least 5 flagged points within 1 mm, and at least half of all there."""
    within = cdist(points[flagged], points) <= 1.0
    n_all, n_flag = within.sum(axis=1), within[:, flagged].sum(axis=1)
    return points[flagged][(n_flag >= 5) & (n_flag >= 0.5 * n_all)]


def seen_from(points: np.ndarray, eye: np.ndarray) -> np.ndarray:
    sight = points - eye
    return np.abs(sight[:, 2]) / np.linalg.norm(sight, axis=1) >= COS60


def brute_maps(kinematic: list[np.ndarray], views: list[MeasuredView]) -> tuple[np.ndarray, np.ndarray]:
    """IA (tolerance 0.1 mm, incidence 60 deg) and IU (target 3.5 um) written out plainly, with the pairs
    found at the kinematic points and everything else at the moved ones."""
    ia = []
    for j in range(1, len(views)):
        for i in range(j):
            src, dst = brute_pairs(kinematic[j], kinematic[i])
            pj, pi = views[j].points_W, views[i].points_W
            seen = seen_from(pj[src], views[j].T_W_C[:3, 3]) & seen_from(pi[dst], views[i].T_W_C[:3, 3])
            src, dst = src[seen], dst[seen]
            gap = np.abs(views[j].deviation_mm[src] - views[i].deviation_mm[dst])
            ia.append(brute_consistent(pj[src], gap > 0.1))
    info = [np.zeros(len(v.points_W)) for v in views]
    for c, vc in enumerate(views):  # view by view, as the map sums them
        for a in range(len(views)):
            if a == c:
                info[a] += 1.0 / vc.uncertainty_mm**2
            else:
                src, dst = brute_pairs(kinematic[a], kinematic[c])
                info[a][src] += 1.0 / vc.uncertainty_mm[dst] ** 2
    points = np.vstack([v.points_W for v in views])
    iu = brute_consistent(points, 1.0 / np.sqrt(np.concatenate(info)) > 0.0035)
    return np.vstack(ia), iu


def kinematic_pairs(kinematic: list[np.ndarray]) -> PairsOf:
    """The maps' pairs as the inspection keeps them: found once per ordered pair at the kinematic points."""
    cache, trees = PairCache(), [cKDTree(p) for p in kinematic]
    return lambda a, b, link: cache.pairs(a, b, link, kinematic[a], trees[b])


def maps(views: list[MeasuredView], pairs: PairsOf | None) -> tuple[np.ndarray, np.ndarray]:
    ia = accuracy_map(views, normals_up, 0.1, max_incidence_deg=60.0, pairs=pairs)
    return ia, uncertainty_map(views, 0.0035, pairs=pairs)


def test_the_maps_from_kinematic_pairs_equal_a_plain_recomputation() -> None:
    """Corrections of 0.15 mm and 5 mrad (ten times the pillar's), so that pairing before or after them
    differs: the maps from the cached pairs equal the brute-force maps with the pairs found at the
    kinematic points exactly, and not the maps with the pairs found at the moved points."""
    kinematic, views = corrected_views(0.15, 0.005)
    ia, iu = maps(views, kinematic_pairs(kinematic))
    ia_truth, iu_truth = brute_maps(kinematic, views)
    assert len(ia) > 100 and len(iu) > 200  # the disc (and views shifted apart), the single-view strips
    assert np.array_equal(ia, ia_truth) and np.array_equal(iu, iu_truth)
    ia_moved, iu_moved = maps(views, None)
    assert not np.array_equal(ia_moved, ia) and not np.array_equal(iu_moved, iu)


def test_pairing_before_small_corrections_changes_little() -> None:
    """With corrections as the pillar's (tens of um), a pair found at the kinematic points differs from the
    one at the moved points only where the geometry allows it (the nearest within 2 delta of the link
    distance or of the second nearest, delta the two views' largest motion), and the maps change by a few
    points."""
    kinematic, views = corrected_views(0.03, 0.001)
    changed = compared = 0
    for a in range(3):
        for b in range(3):
            if a == b:
                continue
            delta = sum(np.linalg.norm(views[v].points_W - kinematic[v], axis=1).max() for v in (a, b))
            d = np.sort(cdist(kinematic[a], kinematic[b]), axis=1)[:, :2]
            src, dst = brute_pairs(kinematic[a], kinematic[b])
            src_m, dst_m = brute_pairs(views[a].points_W, views[b].points_W)
            before, after = dict(zip(src, dst, strict=True)), dict(zip(src_m, dst_m, strict=True))
            moved = [p for p in set(before) | set(after) if before.get(p) != after.get(p)]
            assert all(abs(d[p, 0] - LINK) < delta or d[p, 1] - d[p, 0] < 2 * delta for p in moved)
            changed, compared = changed + len(moved), compared + len(before)
    assert 0 < changed < 0.1 * compared  # 6.8 %: points 0.2 mm apart, views moved 0.05 mm against each other
    ia, iu = maps(views, kinematic_pairs(kinematic))
    ia_moved, iu_moved = maps(views, None)
    assert abs(len(ia) - len(ia_moved)) <= 0.05 * len(ia_moved) and len(ia_moved) > 50
    assert abs(len(iu) - len(iu_moved)) <= 0.05 * len(iu_moved) and len(iu_moved) > 200


def test_a_view_measured_again_is_paired_anew() -> None:
    """The pairs are kept by view index: a view decoded again (a failed decode redone) must not find the
    pairs of its first measurement."""
    kinematic, _ = corrected_views(0.0, 0.0)
    cache, tree = PairCache(), cKDTree(kinematic[0])
    first = cache.pairs(1, 0, LINK, kinematic[1], tree)
    again = kinematic[1] + [0.0, 0.0, 0.45]  # measured again 0.45 mm higher: fewer points within the link
    assert cache.pairs(1, 0, LINK, again, tree)[0] is first[0]  # kept
    cache.forget(1)
    src, dst = cache.pairs(1, 0, LINK, again, tree)
    truth = brute_pairs(again, kinematic[0])
    assert np.array_equal(src, truth[0]) and np.array_equal(dst, truth[1]) and len(src) < len(first[0])


# ---------------------------------------------------------------- the incidence check's nominal normals
def test_the_incidence_check_takes_the_normal_of_the_points_nominal_triangle() -> None:
    """Two views of a 40 x 40 x 10 mm box's top face, 0.2 mm apart, in the 1.5 mm strip along its +x edge,
    both seen straight from above (0 deg incidence on the top face, 90 deg on the side face): the whole strip
    is compared and flagged. The nominal normal of each point as the inspection carries it (its closest
    triangle's, found with its deviation) is the top face's, the truth, but at the edge itself; the nearest
    of the plan's surface samples (1 per mm^2, as the feedback planner's lookup finds them) lies on the side
    face for part of the strip, whose pairs then look grazing and are not compared."""
    box = trimesh.creation.box((40.0, 40.0, 10.0))
    nominal = NominalMesh.from_trimesh(box)
    rng = np.random.default_rng(3)
    views = []
    for v, offset in enumerate((0.0, 0.2)):
        xy = rng.uniform([18.5, -10.0], [20.0, 10.0], (3000, 2))
        points = np.column_stack([xy, 5.0 + offset + rng.normal(0.0, 0.005, len(xy))])
        error_map = signed_distance(nominal, points)
        views.append(
            MeasuredView(
                make_pose(np.eye(3), [0.0, 0.0, 400.0 + v]),
                points,
                deviation_mm=error_map.deviation_mm,
                nominal_normals_W=nominal.face_normals[error_map.face],
            )
        )
    samples, face = trimesh.sample.sample_surface(box, int(box.area), seed=0)
    sample_normals, tree = box.face_normals[face], cKDTree(samples)

    def nearest_sample_normal(points: np.ndarray) -> np.ndarray:
        return sample_normals[tree.query(points)[1]]

    points = np.vstack([v.points_W for v in views])
    top = np.all(np.vstack([v.nominal_normals_W for v in views]) == UP, axis=1)
    # the others: points just inside the material (the noise) nearer to the side face than to the top
    assert top.mean() > 0.99 and np.all(points[~top, 0] > 19.98)
    assert np.mean(np.any(nearest_sample_normal(points) != UP, axis=1)) > 0.05

    flagged = accuracy_map(views, nearest_sample_normal, 0.1, max_incidence_deg=60.0)
    assert len(flagged) > 0.9 * len(views[1].points_W)
    from_samples = [MeasuredView(v.T_W_C, v.points_W, deviation_mm=v.deviation_mm) for v in views]
    assert len(accuracy_map(from_samples, nearest_sample_normal, 0.1, max_incidence_deg=60.0)) < 0.9 * len(
        flagged
    )
