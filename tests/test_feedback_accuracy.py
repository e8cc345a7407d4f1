"""The accuracy map IA (eq 3.9) against planted truth: views of a plane z = 0 whose points are offset by known
amounts, seen by cameras at known incidence."""

from __future__ import annotations

import numpy as np
import pytest

from cell.geometry import make_pose
from cell.planning.feedback import accuracy_map, uncertainty_map
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
