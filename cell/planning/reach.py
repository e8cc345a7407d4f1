"""Can the robot put the sensor at a viewpoint? IK within joint limits away from the wrist singularity, flange
inside the configured envelope, and the sensor body clear of table and part; along a path also the arm's own
links (capsules, cell.planning.arm_body).

The sensor body is approximated by points in the flange frame {T}: the flange, the camera and projector
centres and points along the bar joining them; each must stay ``clearance_mm`` above the table (z = 0 of {W})
and away
from the part surface (nearest-neighbour distance to the part's vertices and surface samples, SciPy KD-tree).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.config import CellConfig
from cell.contracts import Envelope
from cell.geometry import Pose, invert, transform_points
from cell.planning.arm_body import UR5E_CAPSULES, Capsule, arm_samples
from cell.planning.kinematics import UR5E, URKinematics

Array = NDArray[np.float64]


def sensor_body_points_T(cfg: CellConfig, n_bar: int = 8) -> Array:
    """Points (M, 3) of the sensor body in the flange frame (mm): flange, camera, projector and the bar."""
    T_T_C = cfg.sensor.T_T_C.matrix()
    T_T_P = T_T_C @ cfg.sensor.projector.T_C_P.matrix()
    cam, proj = T_T_C[:3, 3], T_T_P[:3, 3]
    bar = cam + np.linspace(0, 1, n_bar)[:, None] * (proj - cam)
    return np.vstack([np.zeros((1, 3)), bar])


class ReachChecker:
    """Reachability of camera poses T_W_C for one cell and one part (surface points in world mm)."""

    def __init__(
        self,
        cfg: CellConfig,
        part_points_W: Array,
        clearance_mm: float,
        kinematics: URKinematics = UR5E,
        arm: tuple[Capsule, ...] = UR5E_CAPSULES,
    ):
        self.T_W_B = cfg.robot.T_W_B.matrix()
        self.T_B_W = invert(self.T_W_B)
        self.T_C_T = invert(cfg.sensor.T_T_C.matrix())
        self.envelope = Envelope(cfg.robot.envelope_min_mm, cfg.robot.envelope_max_mm)
        self.body_T = sensor_body_points_T(cfg)
        self.tree = cKDTree(part_points_W)
        self.clearance = clearance_mm
        self.kin = kinematics
        self.arm = arm

    def _near(self, points_W: Array, within_mm: float) -> NDArray[np.float64]:
        """Distance (mm) of each point to the part's nearest point, exact where it is at most ``within_mm``
        and inf beyond: the search stops there, which makes a path's thousands of arm points, mostly far
        from the part, several times cheaper to check (the same answer for every clearance test)."""
        return np.asarray(self.tree.query(points_W, distance_upper_bound=within_mm + 1.0)[0])

    def target(self, T_W_C: Pose) -> Pose:
        """Flange target T_B_T = inv(T_W_B) @ T_W_C @ inv(T_T_C)."""
        return self.T_B_W @ T_W_C @ self.T_C_T

    def check(self, T_W_C: Pose) -> tuple[bool, str]:
        """(ok, reason); reason says which check failed with the numbers."""
        T_B_T = self.target(T_W_C)
        return self._body_check(T_B_T) or self.kin.reachable(T_B_T)

    def check_many(self, T_W_C: list[Pose]) -> list[tuple[bool, str]]:
        """:meth:`check` of each pose, the IK of those the body checks pass solved in one batch."""
        T_B_T = [self.target(T) for T in T_W_C]
        out = [self._body_check(T) for T in T_B_T]
        todo = [i for i, r in enumerate(out) if r is None]
        if todo:
            for i, r in zip(todo, self.kin.reachable_each(np.stack([T_B_T[i] for i in todo])), strict=True):
                out[i] = r
        return [r for r in out if r is not None]

    def _body_check(self, T_B_T: Pose) -> tuple[bool, str] | None:
        """Why the flange target or the sensor body there fails (envelope, table, part); None if neither."""
        if not self.envelope.contains(T_B_T[:3, 3]):
            return False, f"flange {np.round(T_B_T[:3, 3], 1).tolist()} mm (base) outside the envelope"
        body_W = transform_points(self.T_W_B @ T_B_T, self.body_T)
        low = body_W[:, 2].min()
        if low < self.clearance:
            return False, f"sensor body {low:.1f} mm above the table, needs {self.clearance:.0f} mm"
        d = self._near(body_W, self.clearance)
        if np.min(d) < self.clearance:
            return False, f"sensor body {np.min(d):.1f} mm from the part, needs {self.clearance:.0f} mm"
        return None

    def path_clear(self, T_B_T: NDArray[np.float64]) -> tuple[bool, str]:
        """Flange inside the envelope and sensor body clear of table and part at every flange pose of a
        (N, 4, 4) stack (a sampled path)."""
        p = T_B_T[:, :3, 3]
        lo, hi = np.asarray(self.envelope.min_mm), np.asarray(self.envelope.max_mm)
        outside = np.any((p < lo - 1e-6) | (p > hi + 1e-6), axis=1)
        if outside.any():
            where = np.round(p[np.argmax(outside)], 1).tolist()
            return False, f"flange leaves the envelope on the way at {where} mm (base)"
        T_W_T = np.einsum("ij,njk->nik", self.T_W_B, T_B_T)
        body_W = np.einsum("nij,mj->nmi", T_W_T[:, :3, :3], self.body_T) + T_W_T[:, None, :3, 3]
        low = body_W[..., 2].min()
        if low < self.clearance:
            return (
                False,
                f"sensor body {low:.1f} mm above the table on the way, needs {self.clearance:.0f} mm",
            )
        d = self._near(body_W.reshape(-1, 3), self.clearance)
        if np.min(d) < self.clearance:
            return (
                False,
                f"sensor body {np.min(d):.1f} mm from the part on the way, needs {self.clearance:.0f} mm",
            )
        return True, "clear"

    def arm_clear(self, q: NDArray[np.float64]) -> tuple[bool, str]:
        """Every link capsule of the arm ``clearance_mm`` clear of the table (z = 0 of {W}) and of the part at
        every joint configuration of a (N, 6) stack (a sampled path), rad."""
        arm = arm_samples(self.kin, q, self.arm)
        pts_W = np.einsum("ij,nmj->nmi", self.T_W_B[:3, :3], arm.points_B) + self.T_W_B[:3, 3]
        need = arm.radius_mm + self.clearance  # axis to obstacle
        low = pts_W[..., 2] - need
        if low.min() < 0:
            n, m = np.unravel_index(int(np.argmin(low)), low.shape)
            return False, (
                f"robot {arm.link[m]} {pts_W[n, m, 2] - arm.radius_mm[m]:.1f} mm above the table on the way, "
                f"needs {self.clearance:.0f} mm"
            )
        d = self._near(pts_W.reshape(-1, 3), float(need.max())).reshape(low.shape)
        gap = d - need
        if gap.min() < 0:
            n, m = np.unravel_index(int(np.argmin(gap)), gap.shape)
            return False, (
                f"robot {arm.link[m]} {d[n, m] - arm.radius_mm[m]:.1f} mm from the part on the way, "
                f"needs {self.clearance:.0f} mm"
            )
        return True, "clear"
