"""The one judging pipeline of every report (inspection, ``cell compare``, glass).

Measured points in the part frame {P} (mm) -> signed deviations from the nominal
(:mod:`cell.analysis.errormap`, + outside the material) -> each point's tolerance band (user regions,
:func:`point_bands`) -> isolated out-of-tolerance points set aside -> the :class:`ReportInput` whose
verdict, regions and coverage :func:`cell.analysis.report.write_report` judges and writes. Every job judges
the same way; only what it measured and the context it reports differ.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.analysis.decision import DecisionRule, shrunk
from cell.analysis.errormap import ErrorMap, NominalMesh, signed_distance
from cell.analysis.regions import Coverage, Region, Tolerance, point_bands
from cell.analysis.report import ReportInput, StoredCloud, default_link_radius, isolated_out_of_tolerance
from cell.analysis.report_files import decode_uncertainty, encode_uncertainty


def judge(
    nominal: NominalMesh,
    points_mm: NDArray[np.float64],
    tolerance: Tolerance,
    *,
    n_points_input: int | None = None,
    regions: Sequence[Region] = (),
    min_defect_points: int = 1,
    excluded: Mapping[str, int] | None = None,
    coverage: Coverage | Callable[[ErrorMap], Coverage] | None = None,
    min_coverage: float | None = None,
    link_radius_mm: float | None = None,
    warnings: Sequence[str] = (),
    incomplete_reasons: Sequence[str] = (),
    alignment: dict[str, Any] | None = None,
    calibration: dict[str, Any] | None = None,
    metadata: dict[str, Any] | None = None,
    error_map: ErrorMap | None = None,
    point_fields: Mapping[str, NDArray[Any]] | None = None,
    uncertainty_mm: NDArray[np.floating] | None = None,
    decision: DecisionRule | None = None,
    uncertainty: dict[str, Any] | None = None,
) -> ReportInput:
    """The report input of ``points_mm`` (N, 3, part frame, finite) against ``nominal`` (same frame).

    Out-of-tolerance clusters of fewer than ``min_defect_points`` points are isolated outliers (mixed pixels,
    noise spikes): left out and counted under ``excluded`` as ``isolated_out_of_tolerance_points`` (1, the
    default, keeps every point and adds no count). ``excluded``: what the caller left out before (counts by
    reason), reported after the nominal's own exclusions. ``coverage``: the coverage, or how to compute it
    from the error map of every given point (e.g. from their closest nominal points). ``n_points_input``:
    the points measured (default: those given). ``warnings`` follow the nominal's sign warning;
    ``point_fields``: more values per given point for cloud.ply (e.g. normals). cloud.ply stores every given
    point in order, isolated outliers flagged (:class:`StoredCloud`), so a report rebuilt from it judges the
    same points. ``error_map``: the points' signed distances when the caller computed them already (``cell
    compare`` crops by them), else computed here. ``uncertainty_mm``: each given point's standard
    uncertainty (cell.analysis.uncertainty; stored in cloud.ply as ``uncertainty``); ``decision``: the rule
    that judges the points with it (default: simple): under the guarded rule the isolated outliers are the
    small clusters of points that do not conform (ambiguous or out). The other arguments go to
    :class:`ReportInput` as they are.
    """
    em = signed_distance(nominal, points_mm) if error_map is None else error_map
    faces = nominal.source_face[em.face] if nominal.source_face is not None else em.face
    points, deviation = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3), em.deviation_mm
    counts: dict[str, int] = {**nominal.excluded, **(excluded or {})}
    rule = decision or DecisionRule()
    # as cloud.ply stores it (0.1 um steps, rounded up): a report rebuilt from the file judges the same
    fields = dict(point_fields or {})
    u = None
    if uncertainty_mm is not None:
        fields["uncertainty"] = encode_uncertainty(np.ravel(uncertainty_mm))  # its codes decode to u
        u = decode_uncertainty(fields["uncertainty"])
    stored = None
    if min_defect_points > 1 or fields:
        stored = StoredCloud(points, deviation, fields=fields)
    if min_defect_points > 1:
        bands = shrunk(point_bands(regions, points, faces, tolerance), rule.guard_mm(len(points), u))
        if link_radius_mm is None and bands.outside(deviation).any():  # found once, for the regions too
            link_radius_mm = default_link_radius(points)
        isolated = isolated_out_of_tolerance(points, deviation, bands, min_defect_points, link_radius_mm)
        counts["isolated_out_of_tolerance_points"] = int(isolated.sum())
        if stored is not None:
            stored.isolated = isolated
        if isolated.any():  # else every point is judged: no copies
            kept = ~isolated
            points, deviation, faces = points[kept], deviation[kept], faces[kept]
            u = None if u is None else u[kept]
    return ReportInput(
        points_mm=points,
        deviation_mm=deviation,
        tolerance=tolerance,
        n_points_input=len(points_mm) if n_points_input is None else int(n_points_input),
        excluded=counts,
        metadata=metadata if metadata is not None else {},
        source_face=faces,
        regions=list(regions),
        coverage=coverage(em) if callable(coverage) else coverage,
        min_coverage=min_coverage,
        link_radius_mm=link_radius_mm,
        warnings=[w for w in (nominal.sign_warning(),) if w] + list(warnings),
        incomplete_reasons=list(incomplete_reasons),
        alignment=alignment,
        calibration=calibration,
        stored=stored,
        uncertainty_mm=u,
        decision=rule,
        uncertainty=uncertainty,
    )
