"""The VDI/VDE 2634 Part 3 layout: the sensor moves between views on the robot, and the long ball bar (about
300 mm, longer than one view's field) is measured across views (cell/verification/job.py runs it).

Each bar position lies in the table's plane at the height of the single-view volume's centre; each sphere is
measured from two views (the sensor over the sphere, shifted 40 mm either way along the bar), so the bar spans
four views. Points go to the world with the cell's believed flange pose and the active hand-eye, exactly as
an inspection merges its views, so SD here contains the robot's and the hand-eye's errors.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.geometry import make_pose
from cell.verification.procedure import (
    VOLUME_CENTRE_HEIGHT_MM,
)

BAR_DIRECTIONS_DEG = {"along x": 0.0, "along y": 90.0, "diagonal": 45.0}  # in the table plane
VIEW_SHIFT_MM = 40.0  # each sphere is seen from the view over it shifted this far either way along the bar


def bar_pose(direction_deg: float) -> NDArray[np.float64]:
    """T_W_A of the long bar: centred over the world origin at the volume-centre height, x along the
    direction in the table plane."""
    a = np.deg2rad(direction_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    return make_pose(R, (0.0, 0.0, VOLUME_CENTRE_HEIGHT_MM))


def view_targets(T_W_A: NDArray[np.float64], length_mm: float) -> list[NDArray[np.float64]]:
    """The world points the sensor looks straight down at: two per sphere."""
    axis, centre = T_W_A[:3, 0], T_W_A[:3, 3]
    return [
        centre + axis * (sign * length_mm / 2 + shift)
        for sign in (-1, 1)
        for shift in (-VIEW_SHIFT_MM, VIEW_SHIFT_MM)
    ]
