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


def box_mesh() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(120.0, 90.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))
    return box


def measured_box(n_points: int = 40_000, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Points on the box (mm) with a dent and a bump (and 10 um noise), the +y side's x > 20 part and the
    underside unmeasured; and their true deviations."""
    mesh = box_mesh()
    rng = np.random.default_rng(seed)
    pts, face = trimesh.sample.sample_surface(mesh, int(n_points * 1.3), seed=seed)
    normal = mesh.face_normals[face]
    keep = (normal[:, 2] > -0.5) & ~((normal[:, 1] > 0.5) & (pts[:, 0] > 20.0))
    pts, normal = pts[keep][:n_points], normal[keep][:n_points]
    dev = -0.6 * np.exp(-np.sum((pts - DENT_AT) ** 2, axis=1) / (2 * 5.0**2)) * (normal[:, 2] > 0.5)
    dev += 0.45 * np.exp(-np.sum((pts - BUMP_AT) ** 2, axis=1) / (2 * 4.0**2)) * (normal[:, 1] < -0.5)
    dev += rng.normal(0.0, 0.01, len(pts))
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
