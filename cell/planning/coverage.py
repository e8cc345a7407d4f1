"""Coverage: the share of the inspectable nominal surface with measured points at the required density.

A surface sample counts as covered when the measured points within ``radius_mm`` of it number at least half of
what the required density puts in that disc (half: a sample on a free edge sees only half a disc of surface).
Predicted coverage uses the sensor model instead of measured points.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.geometry import Pose, invert, transform_points
from cell.planning.sensor_model import SensorModel
from cell.planning.surface import PartSurface


def covered_by_points(
    surface: PartSurface, measured_W: NDArray[np.float64], density_per_mm2: float, radius_mm: float
) -> NDArray[np.bool_]:
    """Per sample: enough measured points (world mm) near it."""
    if len(measured_W) == 0:
        return np.zeros(len(surface.points), dtype=bool)
    need = max(1, int(np.ceil(0.5 * density_per_mm2 * np.pi * radius_mm**2)))
    counts = cKDTree(measured_W).query_ball_point(surface.points, radius_mm, return_length=True)
    return np.asarray(counts) >= need


def covered_by_views(
    surface: PartSurface,
    views: Sequence[tuple[cKDTree | None, Pose]],
    density_per_mm2: float,
    radius_mm: float,
    samples: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """:func:`covered_by_points` of several views' points, each view given as a KD-tree of its points in its
    own frame and the pose ``T`` that moves them into the world: the samples are moved into each view's frame
    (a rigid motion keeps distances) and the points near them counted there, so no tree of the moved points is
    built. The same answer as the union's counts: a sample is counted until it is covered (a later view's
    points would not uncover it), so the views after the first that covers a sample do not count it again;
    and a view counts at most the ``need`` points a sample asks for (its nearest within the radius: a
    k-nearest query, half the CPU of counting every point in the disc), which decides the same (but that a
    point whose squared distance falls between fl(r^2) and fl(nextafter(r)^2) counts: the query's bound
    is the next float above the radius, so a point at the radius counts, as the closed disc wants).
    ``samples``: which samples to count (e.g. the inspectable ones); the others are given as not covered."""
    need = max(1, int(np.ceil(0.5 * density_per_mm2 * np.pi * radius_mm**2)))
    counts = np.zeros(len(surface.points), dtype=np.int64)
    # the samples not covered yet
    open_ = np.arange(len(surface.points)) if samples is None else np.flatnonzero(samples)
    # the k-nearest query's bound is strict, the disc's closed: the next float up takes a point at the radius
    bound = float(np.nextafter(radius_mm, np.inf))
    for tree, T in views:
        if tree is None or tree.n == 0 or not len(open_):
            continue
        local = transform_points(invert(T), surface.points[open_])
        near = np.all((local >= tree.mins - radius_mm) & (local <= tree.maxes + radius_mm), axis=1)
        at = open_[near]
        d, _ = tree.query(local[near], k=need, distance_upper_bound=bound)
        counts[at] += np.isfinite(np.asarray(d).reshape(len(at), need)).sum(axis=1)
        open_ = open_[counts[open_] < need]
    return counts >= need


def coverage_fraction(surface: PartSurface, covered: NDArray[np.bool_]) -> float:
    """Covered share of the inspectable area."""
    ins = surface.inspectable
    total = surface.area[ins].sum()
    return float(surface.area[ins & covered].sum() / total) if total > 0 else 0.0


def predicted_masks(sensor: SensorModel, surface: PartSurface, poses: list[Pose]) -> NDArray[np.bool_]:
    """(V, N) which samples each pose is predicted to measure."""
    out = np.zeros((len(poses), len(surface.points)), dtype=bool)
    ins = np.flatnonzero(surface.inspectable)
    for k, T in enumerate(poses):
        out[k, ins] = sensor.measurable(T, surface.points[ins], surface.normals[ins], surface.occluder)
    return out
