"""Motion between viewpoints: retract, traverse, approach.

A straight line between two sensor poses close to the part can sweep the 430 mm sensor bar through the part or
the table, although both poses are clear. The cell therefore lifts the flange straight up to a common safe
height, crosses at that height while turning to the target orientation, and descends onto the target. Heights are
along the base frame's z axis, which is vertical in every cell we build (the base stands upright).
"""

from __future__ import annotations

import numpy as np

from cell.geometry import Pose


def via_points(T_B_T_from: Pose, T_B_T_to: Pose, lift_mm: float, z_max_mm: float) -> list[Pose]:
    """Waypoints (T_B_T, mm) from one flange pose to another: up, across, down. The target is the last one."""
    z_safe = min(max(T_B_T_from[2, 3], T_B_T_to[2, 3]) + lift_mm, z_max_mm)
    up = T_B_T_from.copy()
    up[2, 3] = max(z_safe, T_B_T_from[2, 3])
    across = T_B_T_to.copy()
    across[2, 3] = max(z_safe, T_B_T_to[2, 3])
    path = [up, across, T_B_T_to]
    return [T for k, T in enumerate(path) if k == len(path) - 1 or not np.allclose(T, T_B_T_from)]
