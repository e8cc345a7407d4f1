"""A synthetic report input for the report tests: a 120 x 90 x 40 mm box measured on its top and sides, with
a dent in the top and a bump on the front (known position, depth and height), one patch of the +y side left
unmeasured, and the run metadata an inspection records. Built with the real judging pipeline
(:func:`cell.analysis.judge.judge`) in about a second."""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh

from cell.analysis.errormap import ErrorMap, NominalMesh
from cell.analysis.judge import judge
from cell.analysis.regions import Coverage, Region, Tolerance, coverage
from cell.analysis.report import ReportInput

DENT_AT = np.array([20.0, 10.0, 40.0])  # on the top face; depth 0.6 mm (Gaussian, sigma 5 mm)
BUMP_AT = np.array([-30.0, -45.0, 20.0])  # on the front face (-y); height 0.45 mm (sigma 4 mm)
SPIKES = 5  # single points 0.9 mm high on the top face, far apart


def box_mesh() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))
    return box


def _box_faces(spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on a regular grid of ``spacing`` mm on the box's top and four sides, and their normals."""
    half = np.array([60.0, 45.0, 20.0])
    pts, normals = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            if axis == 2 and sign < 0:
                continue  # the underside, on the table
            u, v = [k for k in range(3) if k != axis]
            gu = np.arange(-half[u] + spacing / 2, half[u], spacing)
            gv = np.arange(-half[v] + spacing / 2, half[v], spacing)
            grid = np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)
            p = np.zeros((len(grid), 3))
            p[:, axis], p[:, u], p[:, v] = sign * half[axis], grid[:, 0], grid[:, 1]
            n = np.zeros_like(p)
            n[:, axis] = sign
            pts.append(p + [0.0, 0.0, 20.0])
            normals.append(n)
    return np.vstack(pts), np.vstack(normals)


def measured_box(n_points: int = 40_000, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """About ``n_points`` points on the box (mm), evenly spaced as a scanner's cloud merged on a voxel grid
    is, with a dent, a bump, :data:`SPIKES` isolated spikes (and 10 um noise); the +y side's x > 20 part
    and the underside unmeasured; and their true deviations."""
    rng = np.random.default_rng(seed)
    area = 120 * 90 + 2 * (120 + 90) * 40  # top and sides, mm^2
    pts, normal = _box_faces(float(np.sqrt(area / n_points)))
    keep = ~((normal[:, 1] > 0.5) & (pts[:, 0] > 20.0))
    pts, normal = pts[keep], normal[keep]
    dev = -0.6 * np.exp(-np.sum((pts - DENT_AT) ** 2, axis=1) / (2 * 5.0**2)) * (normal[:, 2] > 0.5)
    dev += 0.45 * np.exp(-np.sum((pts - BUMP_AT) ** 2, axis=1) / (2 * 4.0**2)) * (normal[:, 1] < -0.5)
    dev += rng.normal(0.0, 0.01, len(pts))
    spikes = np.flatnonzero((normal[:, 2] > 0.5) & (pts[:, 0] < -20))[:: max(1, n_points // 40)][:SPIKES]
    dev[spikes] = 0.9  # single-point spikes (mixed pixels): isolated outliers, not a defect
    return pts + normal * dev[:, None], dev


def synthetic_input(
    name: str = "box",
    region_name: str = "top face",
    tolerance: tuple[float, float] = (-0.3, 0.3),
    n_points: int = 40_000,
    metadata: dict[str, Any] | None = None,
    min_defect_points: int = 10,
) -> ReportInput:
    """The report input of :func:`measured_box` against the box, with a user region on the top face and
    coverage at 0.2 points/mm^2 (radius 3 mm)."""
    mesh = box_mesh()
    nominal = NominalMesh.from_trimesh(mesh)
    pts, _ = measured_box(n_points)
    top = [int(i) for i in np.flatnonzero(mesh.face_normals[:, 2] > 0.5)]

    def measured_coverage(em: ErrorMap) -> Coverage:
        return coverage(nominal, em.closest_mm, 0.2, 3.0)

    return judge(
        nominal,
        pts,
        Tolerance(*tolerance),
        regions=[Region(region_name, faces=np.asarray(top))],
        min_defect_points=min_defect_points,
        coverage=measured_coverage,
        min_coverage=0.6,
        metadata={
            "part": name,
            "cad": "box.stl",
            "run": {
                "folder": f"{name}-SN1-20261126T101500Z",
                "started_utc": "2026-11-26T10:15:00+00:00",
                "identity": {"serial": "SN-0042", "operator": "A. Operator", "order": "PO-7"},
                "recipe": {"file": "box.yaml", "sha256": "ab" * 32},
                "cell": {"name": "sim-binned", "file": "sim_binned.yaml", "sha256": "cd" * 32},
            },
            **(metadata or {}),
        },
    )
