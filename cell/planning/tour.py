"""Order viewpoints to shorten robot motion: nearest neighbour, then 2-opt (segment reversal) until no move
improves. Cost between two camera poses: distance of the camera centres (mm) plus ``mm_per_rad`` times the
rotation between them. Hand-written because SciPy has no TSP heuristic and the tours here are tens of nodes.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.geometry import Pose


def pose_costs(poses: list[Pose], mm_per_rad: float = 200.0) -> NDArray[np.float64]:
    """Symmetric (N, N) motion cost matrix."""
    P = np.array([T[:3, 3] for T in poses])
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in poses]))
    dist = np.linalg.norm(P[:, None] - P[None], axis=-1)
    ang = np.array([(R[i].inv() * R).magnitude() for i in range(len(poses))])
    return dist + mm_per_rad * ang


def order_tour(cost: NDArray[np.float64], start: int = 0) -> list[int]:
    """Open path through all nodes starting at ``start``: nearest neighbour then 2-opt."""
    n = len(cost)
    if n <= 2:
        return list(range(n)) if start == 0 else [start] + [i for i in range(n) if i != start]
    tour = [start]
    left = set(range(n)) - {start}
    while left:
        nxt = min(left, key=lambda j: cost[tour[-1], j])
        tour.append(nxt)
        left.remove(nxt)
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            for k in range(i + 1, n):
                a, b = tour[i - 1], tour[i]
                c = tour[k]
                d = tour[k + 1] if k + 1 < n else None
                old = cost[a, b] + (cost[c, d] if d is not None else 0.0)
                new = cost[a, c] + (cost[b, d] if d is not None else 0.0)
                if new < old - 1e-9:
                    tour[i : k + 1] = tour[i : k + 1][::-1]
                    improved = True
    return tour


def tour_length(cost: NDArray[np.float64], tour: list[int]) -> float:
    return float(sum(cost[a, b] for a, b in zip(tour[:-1], tour[1:])))
