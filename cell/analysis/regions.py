"""Inspection regions, their verdicts, and coverage of the nominal surface by measured points.

A user region is a set of nominal faces (indices into the mesh as given) or an axis-aligned box in the part
frame {P} (mm), with an optional tolerance of its own. A point belongs to a face region when its closest
nominal triangle is one of the region's faces, to a box region when it lies in the box.

Coverage is the fraction of the nominal surface area that has measured points at a required density: the
nominal surface is sampled uniformly by area (seeded, so reports are reproducible); a sample is covered when
at least ``min_count`` measured points project (their closest nominal point) within ``radius_mm`` of it, with
``min_count = ceil(density * pi * radius^2)``. Each sample stands for area / n_samples, so the covered area
has a sampling error of about sqrt(f (1 - f) / n_samples) of the total.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError

if (
    TYPE_CHECKING
):  # the config schemas (pydantic), trimesh and scipy load where used: `cell compare` starts fast
    from cell.analysis.errormap import NominalMesh
    from cell.config import RegionConfig


@dataclass(frozen=True)
class Tolerance:
    """Tolerance band in mm: a deviation d passes when lower_mm <= d <= upper_mm."""

    lower_mm: float = -0.3
    upper_mm: float = 0.3

    def outside(self, deviation_mm: NDArray) -> NDArray[np.bool_]:
        """Deviations outside the band."""
        return (deviation_mm < self.lower_mm) | (deviation_mm > self.upper_mm)


@dataclass(frozen=True)
class Region:
    """A user region: ``faces`` (indices into the nominal mesh as given) or ``box_mm`` ((lo xyz, hi xyz) in
    the part frame); ``tolerance`` overrides the report's band inside the region."""

    name: str
    faces: NDArray[np.int64] | None = None
    box_mm: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    tolerance: Tolerance | None = None

    def contains(self, points_mm: NDArray, source_face: NDArray | None) -> NDArray[np.bool_]:
        """Membership of points (N, 3, mm) with their closest nominal face (index in the mesh as given; a
        face-set region needs it)."""
        if self.faces is not None:
            if source_face is None:
                raise ConfigError(
                    f"region '{self.name}' is a face set but the error map carries no closest faces"
                )
            return np.isin(source_face, self.faces)
        if self.box_mm is None:
            raise ConfigError(f"region '{self.name}' has neither faces nor a box")
        lo, hi = np.asarray(self.box_mm[0]), np.asarray(self.box_mm[1])
        return np.all((points_mm >= lo) & (points_mm <= hi), axis=1)


@dataclass(frozen=True)
class PointBands:
    """The tolerance band each point is judged by (mm, one lower and upper bound per point)."""

    lower_mm: NDArray[np.float64]
    upper_mm: NDArray[np.float64]

    def outside(self, deviation_mm: NDArray) -> NDArray[np.bool_]:
        """Points whose deviation is outside their own band."""
        return (deviation_mm < self.lower_mm) | (deviation_mm > self.upper_mm)


def point_bands(
    regions: Sequence[Region], points_mm: NDArray, source_face: NDArray | None, tol: Tolerance
) -> PointBands:
    """Each point's band: the report's ``tol``, replaced inside user regions with a band of their own; where
    such regions overlap, their intersection (every region's band must hold there, as each region's verdict
    requires)."""
    n = len(points_mm)
    lower, upper = np.full(n, -np.inf), np.full(n, np.inf)
    own = np.zeros(n, dtype=bool)
    for r in regions:
        if r.tolerance is None:
            continue
        if r.faces is not None and source_face is None:
            raise ConfigError(f"region '{r.name}' is a face set but the error map carries no closest faces")
        inside = r.contains(points_mm, source_face)
        lower[inside] = np.maximum(lower[inside], r.tolerance.lower_mm)
        upper[inside] = np.minimum(upper[inside], r.tolerance.upper_mm)
        own |= inside
    lower[~own], upper[~own] = tol.lower_mm, tol.upper_mm
    return PointBands(lower, upper)


def region_from_config(spec: RegionConfig) -> Region:
    """The analysis region of a recipe's or region file's entry."""
    return Region(
        name=spec.name,
        faces=None if spec.faces is None else np.asarray(spec.faces, np.int64),
        box_mm=spec.box_mm,
        tolerance=None if spec.tolerance_mm is None else Tolerance(*spec.tolerance_mm),
    )


def check_region_faces(specs: Sequence[RegionConfig], n_faces: int, path: str | Path, prefix: str) -> None:
    """ConfigError naming the file and field when a face region names a face the nominal does not have."""
    for i, spec in enumerate(specs):
        if spec.faces is not None and max(spec.faces) >= n_faces:
            raise ConfigError(
                f"region '{spec.name}' names face {max(spec.faces)}, but the nominal mesh has {n_faces} "
                f"faces (indices 0..{n_faces - 1}); check the region against the CAD file",
                path=str(path),
                field=f"{prefix}{i}.faces",
            )


def check_face_indices(faces: Sequence[int], n_faces: int, path: str | Path, field: str) -> None:
    """ConfigError naming the file and field when ``faces`` name a face the nominal does not have."""
    if faces and max(faces) >= n_faces:
        raise ConfigError(
            f"face {max(faces)} does not exist: the nominal mesh has {n_faces} faces (indices "
            f"0..{n_faces - 1}); check the list against the CAD file",
            path=str(path),
            field=field,
        )


def load_regions(path: Path) -> list[RegionConfig]:
    """Region specs from YAML (``regions: [{name, faces | box_mm, tolerance_mm}]``), in the schema of a
    recipe's ``regions``: :class:`cell.config.RegionConfig`; errors name the file and field as a recipe's
    do."""
    from cell.analysis.region_file import RegionFile
    from cell.config import read_yaml, validate

    return list(validate(RegionFile, read_yaml(path), path).regions)


@dataclass(frozen=True)
class Coverage:
    """Coverage of the nominal by measured points. ``covered``: per sample; ``samples_mm``/``sample_face``
    (index in the mesh as given) are the area-uniform samples of the nominal surface."""

    fraction: float
    area_mm2: float
    radius_mm: float
    min_count: int
    density_per_mm2: float | None
    samples_mm: NDArray[np.float64]
    sample_face: NDArray[np.int64]
    covered: NDArray[np.bool_]

    def summary(self) -> dict[str, Any]:
        n = len(self.covered)
        return {
            "fraction": self.fraction,
            "covered_area_mm2": self.fraction * self.area_mm2,
            "nominal_area_mm2": self.area_mm2,
            "density_per_mm2": self.density_per_mm2,
            "radius_mm": self.radius_mm,
            "min_count": self.min_count,
            "n_samples": n,
            "sampling_error": math.sqrt(max(self.fraction * (1 - self.fraction), 1.0 / n) / n),
        }


def coverage(
    nominal: NominalMesh,
    closest_mm: NDArray,
    density_per_mm2: float | None = None,
    radius_mm: float | None = None,
    n_samples: int | None = None,
    seed: int = 0,
) -> Coverage:
    """Coverage of the nominal surface by points given as their closest nominal points (N, 3, mm).

    Give a required ``density_per_mm2`` (radius then defaults to the one holding 8 points at that density)
    and/or a ``radius_mm`` (alone: one point within the radius covers).
    """
    if density_per_mm2 is not None and not density_per_mm2 > 0:
        raise ConfigError(f"coverage density must be > 0 points/mm^2, got {density_per_mm2}")
    if radius_mm is None:
        if density_per_mm2 is None:
            raise ConfigError("coverage needs a required density (points/mm^2) or a radius (mm)")
        radius_mm = math.sqrt(8.0 / (math.pi * density_per_mm2))
    if not radius_mm > 0:
        raise ConfigError(f"coverage radius must be > 0 mm, got {radius_mm}")
    min_count = 1 if density_per_mm2 is None else max(1, math.ceil(density_per_mm2 * math.pi * radius_mm**2))
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(nominal.vertices, nominal.faces, process=False)
    area = float(mesh.area)
    if n_samples is None:  # about 4 samples per radius-disc, within [2e3, 2e5]
        n_samples = int(np.clip(4 * area / (math.pi * radius_mm**2), 2_000, 200_000))
    samples, face = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
    closest = np.asarray(closest_mm, dtype=np.float64).reshape(-1, 3)
    if len(closest):
        counts = cKDTree(closest).query_ball_point(samples, radius_mm, return_length=True)
    else:
        counts = np.zeros(len(samples), np.int64)
    covered = counts >= min_count
    src = nominal.source_face if nominal.source_face is not None else np.arange(len(nominal.faces))
    return Coverage(
        fraction=float(covered.mean()),
        area_mm2=area,
        radius_mm=float(radius_mm),
        min_count=int(min_count),
        density_per_mm2=density_per_mm2,
        samples_mm=np.asarray(samples),
        sample_face=src[face],
        covered=covered,
    )


def verdict(n_points: int, n_out: int, coverage_fraction: float | None, min_coverage: float | None) -> str:
    """``no_data`` without points, ``fail`` with any point out of tolerance, ``incomplete`` when coverage is
    below the required fraction, else ``pass``."""
    if n_points == 0:
        return "no_data"
    if n_out:
        return "fail"
    if min_coverage is not None and coverage_fraction is not None and coverage_fraction < min_coverage:
        return "incomplete"
    return "pass"


def region_verdicts(
    regions: Sequence[Region],
    points_mm: NDArray,
    deviation_mm: NDArray,
    source_face: NDArray | None,
    tol: Tolerance,
    cov: Coverage | None = None,
    min_coverage: float | None = None,
    guard_mm: NDArray | None = None,
    ambiguous: str = "incomplete",
) -> list[dict[str, Any]]:
    """Verdict, statistics and coverage of each user region (see docs/report-schema.md). ``guard_mm``: each
    point's U under the guarded decision rule (cell.analysis.decision; None or 0: the simple rule): a point
    beyond the band widened by U is out, one within U of a limit is ambiguous and counts as ``ambiguous``
    says (fail, pass or incomplete)."""
    out = []
    guard = np.zeros(len(deviation_mm)) if guard_mm is None else np.asarray(guard_mm, dtype=np.float64)
    for r in regions:
        if r.faces is not None and source_face is None:
            raise ConfigError(f"region '{r.name}' is a face set but the error map carries no closest faces")
        inside = r.contains(points_mm, source_face)
        d, g = deviation_mm[inside], guard[inside]
        t = r.tolerance or tol
        n_out = int(((d < t.lower_mm - g) | (d > t.upper_mm + g)).sum())
        n_ambiguous = int(((d < t.lower_mm + g) | (d > t.upper_mm - g)).sum()) - n_out
        frac = None
        if cov is not None:
            in_s = (
                np.isin(cov.sample_face, r.faces)
                if r.faces is not None
                else r.contains(cov.samples_mm, cov.sample_face)
            )
            frac = float(cov.covered[in_s].mean()) if in_s.any() else None
        out.append(
            {
                "name": r.name,
                "kind": "faces" if r.faces is not None else "box",
                "tolerance": {"lower_mm": t.lower_mm, "upper_mm": t.upper_mm},
                "n_points": int(len(d)),
                "n_out_of_tolerance": n_out,
                "n_ambiguous": n_ambiguous,
                "mean_mm": float(d.mean()) if len(d) else None,
                "min_mm": float(d.min()) if len(d) else None,
                "max_mm": float(d.max()) if len(d) else None,
                "coverage": frac,
                "verdict": _region_verdict(len(d), n_out, n_ambiguous, frac, min_coverage, ambiguous),
            }
        )
    return out


def _region_verdict(
    n: int, n_out: int, n_ambiguous: int, frac: float | None, min_coverage: float | None, ambiguous: str
) -> str:
    """:func:`verdict` with the ambiguous points counted as ``ambiguous`` says."""
    v = verdict(n, n_out + (n_ambiguous if ambiguous == "fail" else 0), frac, min_coverage)
    return "incomplete" if v == "pass" and n_ambiguous and ambiguous == "incomplete" else v
