"""Greedy set-cover baseline: from a pool of candidate viewpoints, repeatedly take the one that adds the most
uncovered inspectable area until the target coverage is reached (the classic ln(n)-approximation), to compare
view counts with the bounding-box planner on the same candidates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def greedy_cover(masks: NDArray[np.bool_], area: NDArray[np.float64], target_area: float) -> list[int]:
    """Indices of chosen candidates (rows of ``masks``, (V, N)) covering >= ``target_area`` of ``area``."""
    covered = np.zeros(masks.shape[1], dtype=bool)
    chosen: list[int] = []
    while area[covered].sum() < target_area - 1e-9:
        gain = (masks & ~covered) @ area
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(k)
        covered |= masks[k]
    return chosen
