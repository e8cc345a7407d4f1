"""Error map and report of any measured cloud against any nominal mesh (what ``cell compare`` runs).

The nominal goes through :func:`cell.mesh.load_mesh_arrays` and its checks (units, manifoldness, zero-area
faces); the cloud is read from PLY, XYZ or CSV and checked for units against the nominal. Millimetres
throughout, deviations + outside the material.

A whole ``cell compare`` is measured against CloudCompare (bench/bench_compare.py), so this path imports only
what it uses: plain binary STL/PLY files are read with numpy (:mod:`cell.mesh_files`, trimesh only for the
other formats), alignment, regions and coverage import their libraries when asked for.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from cell.analysis.crop import CropMasks, PartCrop
from cell.analysis.errormap import ErrorMap, NominalMesh, signed_distance
from cell.errors import ConfigError
from cell.mesh import load_mesh_arrays

# share of the points off the table that must lie near the nominal surface. Measured on a simulated scan of
# the good pillar (`cell scan --pose auto`, sim_binned): 1.0 in the right frame; 0.0 moved 20 mm up, 0.05
# 20 mm down, 0.47 30 mm across the pillar, 0.38 turned 90 degrees about z; 0.98 moved 50 mm along it (its
# cross-section does not change there: no cloud-only test can see that shift)
MIN_OVERLAP = 0.5
OVERLAP_MM = 5.0  # "near" when background cropping is off: the inspection's crop distance


def load_cloud(path: Path) -> np.ndarray:
    """Points (N, 3, mm) from PLY (vertices), XYZ or CSV (first three numeric columns; header row skipped)."""
    if not path.is_file():
        raise ConfigError("cloud file not found", path=str(path))
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            pts = _read_ply_points(path)
        elif suffix in (".xyz", ".txt", ".csv"):
            delim = "," if suffix == ".csv" else None
            with open(path) as fh:
                first = fh.readline()
            skip = 0 if _is_numeric_row(first, delim) else 1
            pts = np.loadtxt(path, delimiter=delim, skiprows=skip, usecols=(0, 1, 2), ndmin=2)
        else:
            raise ConfigError(f"unknown cloud format '{suffix}': use .ply, .xyz or .csv", path=str(path))
    except (ValueError, OSError) as exc:
        raise ConfigError(f"cannot read the cloud: {exc}", path=str(path)) from exc
    return pts.reshape(-1, 3)


def _read_ply_points(path: Path) -> np.ndarray:
    """A PLY's vertex positions (float64): read with numpy when the file is plain binary, else by trimesh."""
    from cell.mesh_files import read_ply

    plain = read_ply(path, mesh=False)
    if plain is not None:
        return plain.vertices
    import trimesh

    loaded = trimesh.load(path, process=False)
    if not hasattr(loaded, "vertices"):  # trimesh gives an empty Scene for a PLY without vertices
        raise ConfigError("the cloud has no points", path=str(path))
    return np.asarray(loaded.vertices, dtype=np.float64)


def _is_numeric_row(line: str, delim: str | None) -> bool:
    try:
        [float(x) for x in line.strip().split(delim)[:3]]
        return True
    except ValueError:
        return False


def check_units(pts: np.ndarray, nominal: NominalMesh, cloud_path: Path) -> None:
    """ConfigError when the finite points ``pts`` are none, or not the nominal's size (another unit)."""
    if len(pts) == 0:
        raise ConfigError("the cloud has no finite points (empty or all NaN)", path=str(cloud_path))
    ratio = np.linalg.norm(np.ptp(pts, 0)) / nominal.extent_mm
    inches = any(abs(ratio * k - 1) < 0.1 for k in (25.4, 1 / 25.4))
    if len(pts) >= 3 and (not 1 / 30 < ratio < 30 or inches):
        hint = " (a factor of 25.4: inches?)" if inches else ""
        raise ConfigError(
            f"the cloud is {ratio:.3g}x the size of the nominal{hint}: wrong units? (both must be in mm)",
            path=str(cloud_path),
        )


def parse_tolerance(text: str) -> tuple[float, float]:
    """'-0.3,0.3' -> (-0.3, 0.3) mm; limits as plausible as a recipe's (:func:`cell.limits.tolerance_problem`:
    '-0.0003,0.0003' is a band in metres)."""
    from cell.limits import tolerance_problem

    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError as exc:
        raise ConfigError(f"must be 'LOWER,UPPER' in mm, got '{text}'", field="--tolerance") from exc
    if not lo < hi:
        raise ConfigError(f"the lower limit must be below the upper one, got '{text}'", field="--tolerance")
    problem = tolerance_problem(lo, hi)
    if problem:
        raise ConfigError(problem, field="--tolerance")
    return lo, hi


def parse_table_z(text: str | float | None, nominal: NominalMesh) -> float | None:
    """The table top's z in the nominal's frame (mm): 'lowest' (the nominal's lowest point: the part stands on
    the table), a number, or 'none' (no table)."""
    if text is None or str(text).lower() == "none":
        return None
    if str(text).lower() == "lowest":
        return float(nominal.vertices[:, 2].min())
    try:
        return float(text)
    except ValueError as exc:
        raise ConfigError(f"must be 'lowest', 'none' or a z in mm, got '{text}'", field="--table-z") from exc


def crop_to_part(
    nominal: NominalMesh, pts: np.ndarray, crop: PartCrop, cloud_path: Path
) -> tuple[ErrorMap, CropMasks]:
    """The points' error map and what of them is table and background (:class:`PartCrop`, as the inspection
    crops its views). ConfigError when the cloud does not overlap the nominal: fewer than
    :data:`MIN_OVERLAP` of its points off the table lie within the overlap distance of the surface (a cloud
    in another frame: the camera's, a scanner's, the part's placed elsewhere)."""
    em = signed_distance(nominal, pts)
    masks = crop.split(pts, em.deviation_mm)
    off_table = ~masks.on_table
    if not off_table.any():
        raise ConfigError(
            f"no point lies {crop.table_margin_mm} mm or more above the table top (z = {crop.table_z_mm:g} "
            "mm in the nominal's frame): nothing of the part. Is the cloud in another frame (upside down)? "
            "Else give the table's z with --table-z",
            path=str(cloud_path),
        )
    near_mm = crop.background_mm or OVERLAP_MM
    share = float((np.abs(em.deviation_mm[off_table]) <= near_mm).mean())
    if share < MIN_OVERLAP:
        offset = np.median(pts[off_table], axis=0) - 0.5 * (nominal.vertices.min(0) + nominal.vertices.max(0))
        raise ConfigError(
            f"the cloud does not overlap the nominal: {100 * share:.1f}% of its points (off the table) lie "
            f"within {near_mm:g} mm of the nominal surface (at least {100 * MIN_OVERLAP:.0f}% expected); its "
            f"median point is ({', '.join(f'{v:.0f}' for v in offset)}) mm from the nominal's centre. Is it "
            "in another frame? Bring it into the nominal's frame or align it (--align datums); crop a cloud "
            "that is mostly not the part (fixtures, clutter) to the part first",
            path=str(cloud_path),
        )
    return em, masks


def run_compare(
    nominal_path: Path,
    cloud_path: Path,
    out: Path,
    align: str = "none",
    tolerance: str = "-0.3,0.3",
    datums: Path | None = None,
    pictures: bool = True,
    regions: Path | None = None,
    density_per_mm2: float | None = None,
    radius_mm: float | None = None,
    min_coverage: float | None = None,
    min_defect_points: int = 1,
    csv: bool = False,
    table_z: str | float | None = "lowest",
    crop_mm: float | None = 5.0,
) -> dict:
    """Load, check, align, compute the error map and write the report; return report.json's document.

    ``regions``: YAML of user regions (see ``cell.analysis.regions.load_regions``); coverage is computed when
    a required density (points/mm^2) or radius (mm) is given, and judged against ``min_coverage`` (0..1).
    ``min_defect_points``: out-of-tolerance clusters smaller than this are isolated outliers, excluded and
    counted under ``excluded`` as ``cell inspect`` does (1, the default, keeps every point: a cloud from
    elsewhere may have been filtered already). ``csv``: also write deviations.csv (off by default: at 5M
    points the text file takes longer to write than the whole comparison; cloud.ply holds the same numbers).
    ``table_z`` (:func:`parse_table_z`) and ``crop_mm`` (None or 0: keep the background) crop the cloud to
    the part as the inspection crops its views (:class:`cell.analysis.crop.PartCrop`), after the alignment;
    the points left out are counted under ``excluded`` (``table_points``, ``background_points``). A cloud
    that does not overlap the nominal is refused (:func:`crop_to_part`).
    """
    from cell.analysis.judge import judge
    from cell.analysis.regions import (
        Coverage,
        Tolerance,
        check_region_faces,
        coverage,
        load_regions,
        region_from_config,
    )
    from cell.analysis.report import write_report

    lo, hi = parse_tolerance(tolerance)
    if min_coverage is not None and not 0 <= min_coverage <= 1:
        raise ConfigError(f"--min-coverage must be a fraction in [0, 1], got {min_coverage}")
    if crop_mm is not None and crop_mm < 0:
        raise ConfigError(f"must be >= 0 mm (0: keep the background), got {crop_mm}", field="--crop-mm")
    if min_defect_points < 1:
        raise ConfigError(f"--min-defect-points must be >= 1, got {min_defect_points}")
    if min_coverage is not None and density_per_mm2 is None and radius_mm is None:
        raise ConfigError("--min-coverage needs --density (points/mm^2) or --radius (mm) to measure coverage")
    region_specs = load_regions(regions) if regions is not None else []
    if align not in ("none", "datums", "bestfit"):
        raise ConfigError(f"--align must be none, datums or bestfit, got '{align}'")
    mesh = load_mesh_arrays(nominal_path, what="nominal mesh")
    check_region_faces(region_specs, len(mesh.faces), regions or "", prefix="regions.")
    user_regions = [region_from_config(spec) for spec in region_specs]
    t0 = time.perf_counter()
    nominal = NominalMesh.from_arrays(mesh.vertices, mesh.faces)
    crop = PartCrop(parse_table_z(table_z, nominal), background_mm=crop_mm or None)
    raw = load_cloud(cloud_path)
    finite = np.isfinite(raw).all(1)
    pts = raw if finite.all() else raw[finite]  # a copy only when something goes: 120 MB at 5M points
    check_units(pts, nominal, cloud_path)
    T = np.eye(4)
    if align != "none":
        from cell.analysis.registration import datum_align, icp_point_to_plane
        from cell.geometry import transform_points
    if align == "datums":
        if datums is None:
            raise ConfigError(
                "--align datums needs --datums FILE (csv: nominal x,y,z, measured x,y,z per row)"
            )
        d = np.loadtxt(datums, delimiter=",", ndmin=2, comments="#")
        if d.shape[1] != 6:
            raise ConfigError("datum file needs 6 columns: nominal x,y,z, measured x,y,z", path=str(datums))
        T = datum_align(d[:, 3:6], d[:, 0:3])
    elif align == "bestfit":
        # ICP starts where the cloud is, on what is the part there: table and background would pull it
        T = icp_point_to_plane(nominal, pts, region=crop_to_part(nominal, pts, crop, cloud_path)[1].part).T
    if align != "none":  # the identity would only copy millions of points
        pts = transform_points(T, pts)
    em, masks = crop_to_part(nominal, pts, crop, cloud_path)
    keep = masks.part
    kept = pts if keep.all() else pts[keep]
    warning = "best-fit alignment hides global deviations" if align == "bestfit" else None
    meta: dict[str, Any] = {
        "nominal": str(nominal_path),
        "cloud": str(cloud_path),
        "align": align,
        "warning": warning,
        "T_P_cloud": T.round(9).tolist(),
        "nominal_watertight": nominal.watertight,
    }

    def measured_coverage(em: ErrorMap) -> Coverage:
        """Coverage of the nominal by the points' closest nominal points."""
        return coverage(nominal, em.closest_mm, density_per_mm2, radius_mm)

    inp = judge(
        nominal,
        kept,
        Tolerance(lo, hi),
        n_points_input=len(raw),
        regions=user_regions,
        min_defect_points=min_defect_points,
        excluded={
            "non_finite_points": int((~finite).sum()),
            **{f"{reason}_points": n for reason, n in masks.counts().items()},
        },
        coverage=measured_coverage if density_per_mm2 is not None or radius_mm is not None else None,
        min_coverage=min_coverage,
        warnings=[warning] if warning else [],
        metadata=meta,
        error_map=em if keep.all() else em.take(keep),
    )
    meta["seconds"] = round(time.perf_counter() - t0, 3)  # the comparison, error map included
    return write_report(out, inp, pictures=pictures, csv=csv)
