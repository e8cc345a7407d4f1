"""Coverage: the share of the inspectable nominal surface with measured points at the required density.

A surface sample counts as covered when the measured points within ``radius_mm`` of it number at least half of
what the required density puts in that disc (half: a sample on a free edge sees only half a disc of surface).
Predicted coverage uses the sensor model instead of measured points.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.geometry import Pose
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
