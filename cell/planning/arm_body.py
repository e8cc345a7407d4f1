"""The robot arm's own body as capsules, for clearance checks of its links (not only of the sensor).

Each link is a capsule: a segment in one of the DH frames of :meth:`URKinematics.fk_frames` and a radius that
encloses the link tube and its joint housings. The UR5e's links do not lie on the DH skeleton: the upper arm
runs 138 mm along the shoulder axis from it, the forearm 7 mm (138 - 131), and the wrists sit on their own
axes; the segments below carry those offsets. Radii are rounded up from UR's drawings of the UR5e (joint
housings of about 120 mm, 90 mm and 90 mm diameter for the shoulder/elbow, wrist joints); they are
deliberately generous, a clearance check needs a hull, not a model.

Hand-written because no maintained Python library carries UR link geometry; a full URDF collision model
(meshes) would be the upgrade where the capsules prove too coarse.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.planning.kinematics import URKinematics

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Capsule:
    """A link hull: segment ``p0``-``p1`` (mm) in frame ``frame`` of ``fk_frames`` (0 base .. 6 flange)."""

    name: str
    frame: int
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius_mm: float


UR5E_CAPSULES: tuple[Capsule, ...] = (
    Capsule("shoulder", 1, (0.0, 0.0, 0.0), (0.0, 0.0, 138.0), 65.0),
    Capsule("upper arm", 2, (425.0, 0.0, 138.0), (0.0, 0.0, 138.0), 60.0),
    Capsule("elbow", 2, (0.0, 0.0, 7.0), (0.0, 0.0, 138.0), 55.0),
    Capsule("forearm", 3, (392.2, 0.0, 7.0), (0.0, 0.0, 7.0), 50.0),
    Capsule("wrist 1", 3, (0.0, 0.0, 7.0), (0.0, 0.0, 133.3), 45.0),
    Capsule("wrist 2", 4, (0.0, 0.0, 0.0), (0.0, 0.0, 99.7), 45.0),
    Capsule("wrist 3", 5, (0.0, 0.0, 0.0), (0.0, 0.0, 50.0), 45.0),  # stops short of the flange
)


@dataclass(frozen=True)
class ArmSamples:
    """Points along the capsule axes of a stack of joint configurations: ``points_B`` (N, M, 3) mm in {B};
    ``radius_mm`` and ``link`` (M,) say which capsule each column belongs to."""

    points_B: Array
    radius_mm: Array
    link: tuple[str, ...]


def arm_samples(
    kin: URKinematics, q: Array, capsules: tuple[Capsule, ...] = UR5E_CAPSULES, step_mm: float = 20.0
) -> ArmSamples:
    """Capsule axes sampled every ``step_mm`` at joints ``q`` (N, 6) rad. A capsule is clear of an obstacle
    when every sample is more than its radius away, to within step/2 between samples."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    frames = kin.fk_frames(q)  # (N, 7, 4, 4)
    columns, radius, link = [], [], []
    for c in capsules:
        p0, p1 = np.asarray(c.p0), np.asarray(c.p1)
        n = max(2, int(np.ceil(np.linalg.norm(p1 - p0) / step_mm)) + 1)
        local = p0 + np.linspace(0.0, 1.0, n)[:, None] * (p1 - p0)
        F = frames[:, c.frame]
        columns.append(np.einsum("nij,mj->nmi", F[:, :3, :3], local) + F[:, None, :3, 3])
        radius += [c.radius_mm] * n
        link += [c.name] * n
    return ArmSamples(np.concatenate(columns, axis=1), np.asarray(radius), tuple(link))
