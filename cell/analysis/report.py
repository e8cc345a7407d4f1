"""The inspection report of an error map: report.json, report.html, cloud.ply (``deviation``), deviations.csv.

The schema of report.json is documented in docs/report-schema.md, the page in docs/report.md. Deviations in
mm, + outside the material. Out-of-tolerance points are grouped into regions by a radius graph (the groups
of :func:`cell.analysis._point_grid.radius_groups`, as cKDTree pairs + connected components would make
them). The files are written as one set (:mod:`cell.analysis.report_files`): a failed or killed report
leaves the previous one whole, or none. An inspection publishes its verdict first (:func:`write_verdict`:
report.json alone) and writes the rest after it (:func:`write_page`: cloud.ply and report.html with its
pictures and 3D view, seconds of work the verdict does not wait for).
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import cell
from cell.analysis.colour_scale import BandedScale
from cell.analysis.decision import AMBIGUOUS, NONCONFORM, DecisionRule, class_counts, classify, widened
from cell.analysis.formatting import utc_iso
from cell.analysis.regions import (
    Coverage,
    PointBands,
    Region,
    Tolerance,
    point_bands,
    region_verdicts,
    verdict,
)

__all__ = [
    "ReportInput",
    "StoredCloud",
    "Tolerance",
    "out_of_tolerance_regions",
    "summarise",
    "write_page",
    "write_report",
    "write_verdict",
]

SCHEMA_VERSION = 7
PERCENTILES = (1, 5, 25, 50, 75, 95, 99)


@dataclass
class StoredCloud:
    """Every point cloud.ply stores, in the order measured, when that is more than the judged points or
    carries more fields: ``isolated`` marks the points set aside as isolated outliers (not judged; the
    judged points are those not marked, in order); ``fields``: more per-point values (e.g. the glass
    normals ``nx, ny, nz``)."""

    points_mm: NDArray[np.float64]
    deviation_mm: NDArray[np.float64]
    isolated: NDArray[np.bool_] | None = None
    fields: dict[str, NDArray[Any]] = field(default_factory=dict)


@dataclass
class ReportInput:
    """What a report is made of: points (N, 3, mm, part frame), their deviations and the run's context.

    ``source_face``: closest nominal face per point (index in the mesh as given), needed by face regions;
    ``regions``: user regions judged one by one; ``coverage``: of the nominal by the points, with the
    required fraction ``min_coverage`` (below it the verdict is ``incomplete`` unless something fails).
    """

    points_mm: NDArray[np.float64]
    deviation_mm: NDArray[np.float64]
    tolerance: Tolerance
    n_points_input: int
    excluded: dict[str, int] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    source_face: NDArray[np.int64] | None = None
    regions: list[Region] = field(default_factory=list)
    coverage: Coverage | None = None
    min_coverage: float | None = None
    link_radius_mm: float | None = None  # out-of-tolerance points closer than this form one region
    warnings: list[str] = field(default_factory=list)  # what the reader must know before trusting the map
    # why the measurement cannot judge the part (calibration missing/stale/poor, alignment failed): a pass or
    # fail becomes 'incomplete'
    incomplete_reasons: list[str] = field(default_factory=list)
    alignment: dict[str, Any] | None = (
        None  # how the cloud was put into the part frame (cell.analysis.alignment)
    )
    calibration: dict[str, Any] | None = None  # the calibration files used (cell.calibration_state)
    stored: StoredCloud | None = None  # what cloud.ply stores when not just the judged points
    # each point's standard uncertainty u (mm, cell.analysis.uncertainty), None when not known, and the
    # decision rule that judges the points with it (cell.analysis.decision)
    uncertainty_mm: NDArray[np.float64] | None = None
    decision: DecisionRule = field(default_factory=DecisionRule)
    uncertainty: dict[str, Any] | None = None  # the uncertainty budget for the report (where u came from)
    _figures: dict[str, Any] | None = field(default=None, init=False, repr=False)  # :meth:`figures`

    @cached_property
    def bands(self) -> PointBands:
        """The band each point is judged by: the report's, or inside user regions with a band of their own
        that band (:func:`cell.analysis.regions.point_bands`)."""
        return point_bands(self.regions, self.points_mm, self.source_face, self.tolerance)

    @cached_property
    def guard_mm(self) -> NDArray[np.float64]:
        """U of every point under the decision rule (0 under the simple rule)."""
        return self.decision.guard_mm(len(self.deviation_mm), self.uncertainty_mm)

    @cached_property
    def classes(self) -> NDArray[np.int8]:
        """Each point's class under the decision rule (cell.analysis.decision)."""
        return classify(self.deviation_mm, self.bands, self.guard_mm)

    @cached_property
    def nonconforming_band(self) -> Tolerance | PointBands:
        """The band beyond which a point does not conform: the tolerance, widened by U (guarded rule)."""
        return widened(self.bands, self.guard_mm)

    def figures(self, pool: Executor | None = None) -> dict[str, Any]:
        """What report.json says of the points themselves (:func:`point_figures`, with ``pool``), computed
        once."""
        if self._figures is None:
            self._figures = point_figures(self, pool)
        return self._figures


def default_link_radius(points_mm: NDArray) -> float:
    """3x the cloud's median nearest-neighbour spacing: queried for a random sample of points against the
    whole cloud (a thinned cloud would overstate the spacing), duplicates (zero distances) left out."""
    if len(points_mm) < 2:
        return 0.0
    from cell.analysis._point_grid import nearest_other, point_grid

    sample = np.random.default_rng(0).choice(len(points_mm), min(len(points_mm), 20000), replace=False)
    n_same, d = nearest_other(point_grid(points_mm), sample)
    # the nearest point elsewhere, as a k-d tree's 8 nearest give it: none when they are all copies
    d = np.where(n_same < 8, d, np.inf)
    d = d[np.isfinite(d)]
    return 3.0 * float(np.median(d)) if len(d) else 0.0


def out_of_tolerance_clusters(
    points_mm: NDArray,
    deviation_mm: NDArray,
    band: Tolerance | PointBands,
    link_radius_mm: float | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of the points outside their band (one for all, or one per point) and their cluster label
    (points closer than the link radius, by default :func:`default_link_radius`, share a cluster)."""
    return point_clusters(points_mm, band.outside(deviation_mm), link_radius_mm)


def point_clusters(
    points_mm: NDArray, mask: NDArray[np.bool_], link_radius_mm: float | None = None
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of the points in ``mask`` and their cluster label (points closer than the link radius, by
    default :func:`default_link_radius` of all the points, share a cluster)."""
    bad = np.flatnonzero(mask)
    if len(bad) == 0:
        return bad, np.zeros(0, dtype=np.int64)
    from cell.analysis._point_grid import radius_groups

    radius = default_link_radius(points_mm) if link_radius_mm is None else link_radius_mm
    return bad, radius_groups(points_mm[bad], radius)


def isolated_out_of_tolerance(
    points_mm: NDArray,
    deviation_mm: NDArray,
    band: Tolerance | PointBands,
    min_points: int,
    link_radius_mm: float | None = None,
) -> NDArray[np.bool_]:
    """Mask of out-of-tolerance points in clusters of fewer than ``min_points``: isolated outliers (mixed
    pixels at edges, noise spikes) rather than a surface defect, which covers an area."""
    out = np.zeros(len(deviation_mm), dtype=bool)
    bad, lab = out_of_tolerance_clusters(points_mm, deviation_mm, band, link_radius_mm)
    if len(bad):
        sizes = np.bincount(lab)
        out[bad[sizes[lab] < min_points]] = True
    return out


def out_of_tolerance_regions(
    points_mm: NDArray,
    deviation_mm: NDArray,
    band: Tolerance | PointBands,
    link_radius_mm: float | None = None,
    max_regions: int = 20,
) -> list[dict[str, Any]]:
    """Spatial clusters of points outside their band, largest first, with centre and extreme deviation."""
    bad, lab = out_of_tolerance_clusters(points_mm, deviation_mm, band, link_radius_mm)
    if len(bad) == 0:
        return []
    pts = points_mm[bad]
    sizes = np.bincount(lab)
    regions: list[dict[str, Any]] = []
    for r in np.argsort(-sizes)[:max_regions]:
        idx = np.flatnonzero(lab == r)
        dev = deviation_mm[bad[idx]]
        ext = int(idx[np.argmax(np.abs(dev))])
        d_ext = float(deviation_mm[bad[ext]])
        limit = _limit(band, int(bad[ext]), above=d_ext > 0)
        regions.append(
            {
                "name": f"out-of-tolerance-{len(regions) + 1}",
                "verdict": "fail",
                "n_points": int(len(idx)),
                "centre_mm": [round(float(c), 4) for c in pts[idx].mean(0)],
                "extreme_mm": round(float(deviation_mm[bad[ext]]), 5),
                "extreme_at_mm": [round(float(c), 4) for c in pts[ext]],
                "kind": "excess" if d_ext > 0 else "dent",
                "limit_mm": round(limit, 5),
                "beyond_mm": round(d_ext - limit, 5),
            }
        )
    return regions


def _limit(band: Tolerance | PointBands, i: int, above: bool) -> float:
    """The limit a point ``i`` outside its band crossed: its band's upper limit when ``above``, else lower."""
    if isinstance(band, Tolerance):
        return band.upper_mm if above else band.lower_mm
    return float(band.upper_mm[i] if above else band.lower_mm[i])


@lru_cache(maxsize=1)
def _commit() -> str | None:
    """``git describe --always --dirty`` of the checkout the code runs from, or None (an installed package,
    no git)."""
    repo = Path(cell.__file__).resolve().parents[1]
    if not (repo / ".git").exists():
        return None
    try:
        done = subprocess.run(
            ["git", "-C", str(repo), "describe", "--always", "--dirty", "--abbrev=10"],
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None


def software() -> dict[str, str | None]:
    """The software that made the report: package name, version and, in a git checkout, the commit
    (null when installed from a package)."""
    return {"name": "inspection-cell", "version": cell.__version__, "commit": _commit()}


def summarise(inp: ReportInput, views: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The report.json document (see docs/report-schema.md): the points' figures (:func:`point_figures`,
    kept on ``inp``) with the run's context."""
    f = inp.figures()
    overall, reasons = f["verdict"], list(inp.incomplete_reasons)
    if f["ambiguous_reason"] is not None:
        reasons.append(f["ambiguous_reason"])
    if overall in ("pass", "fail") and inp.incomplete_reasons:
        overall = "incomplete"  # a measurement that cannot be trusted neither passes nor fails a part
    tol = inp.tolerance
    return {
        "schema_version": SCHEMA_VERSION,
        "created_utc": utc_iso(time.time()),
        "software": software(),
        "verdict": overall,
        "incomplete_reasons": reasons,
        "tolerance": {"lower_mm": tol.lower_mm, "upper_mm": tol.upper_mm},
        "n_points": f["n_points"],
        "n_points_input": int(inp.n_points_input),
        "n_out_of_tolerance": f["n_out_of_tolerance"],
        "fraction_in_tolerance": f["fraction_in_tolerance"],
        "coverage": f["coverage"],
        "coverage_detail": f["coverage_detail"],
        "min_coverage": inp.min_coverage,
        "deviation": f["deviation"],
        "regions": f["regions"],
        "region_verdicts": f["region_verdicts"],
        "decision": {**inp.decision.to_json(), **f["decision"]},
        "uncertainty": f["uncertainty"],
        "excluded": inp.excluded,
        "views": views or [],
        "warnings": list(inp.warnings),
        "alignment": inp.alignment,
        "calibration": inp.calibration,
        "metadata": inp.metadata,
    }


def point_figures(inp: ReportInput, pool: Executor | None = None) -> dict[str, Any]:
    """What report.json says of the judged points themselves, whatever the run's context (its incomplete
    reasons, metadata, calibration): the deviation statistics, the out-of-tolerance and ambiguous regions,
    the user regions' verdicts, the decision's counts, the points' uncertainty and the verdict before the
    incomplete reasons (``ambiguous_reason``: the one the guarded rule's ambiguous points add, or None).
    Use :meth:`ReportInput.figures` (computed once: an inspection's registration computes them beside the
    evaluation). With a ``pool`` its threads compute the uncertainty's and the deviations' statistics
    meanwhile."""
    u_summary = None if pool is None else pool.submit(uncertainty_summary, inp)
    d = inp.deviation_mm
    d_stats = None if pool is None else pool.submit(deviation_stats, d)
    tol = inp.tolerance
    bands = inp.nonconforming_band  # the tolerance itself under the simple rule
    classes = inp.classes
    inside = classes != NONCONFORM
    cov = inp.coverage
    coverage = cov.fraction if cov is not None else None
    regions = out_of_tolerance_regions(inp.points_mm, d, bands, link_radius_mm=inp.link_radius_mm)
    policy = inp.decision.ambiguous
    user = region_verdicts(
        inp.regions, inp.points_mm, d, inp.source_face, tol, cov, inp.min_coverage, inp.guard_mm, policy
    )
    # Any point outside its band (widened by U under the guarded rule) or any failing region fails the part;
    # any unmeasured region makes it incomplete; ambiguous points count as the recipe says.
    n_ambiguous = int((classes == AMBIGUOUS).sum())
    n_fail = int((~inside).sum()) + (n_ambiguous if policy == "fail" else 0)
    overall = verdict(len(d), n_fail, coverage, inp.min_coverage)
    region_states = {r["verdict"] for r in user}
    if overall != "no_data" and "fail" in region_states:
        overall = "fail"
    elif overall == "pass" and region_states & {"incomplete", "no_data"}:
        overall = "incomplete"
    ambiguous_reason = None
    if overall == "pass" and n_ambiguous and policy == "incomplete":
        overall = "incomplete"
        ambiguous_reason = (
            f"{n_ambiguous} points lie within their expanded uncertainty U of a tolerance limit (ambiguous "
            "under the guarded decision rule): the measurement cannot show them in or out of tolerance"
        )
    return {
        "verdict": overall,
        "ambiguous_reason": ambiguous_reason,
        "n_points": int(len(d)),
        "n_out_of_tolerance": int((~inside).sum()),
        "fraction_in_tolerance": float(inside.mean()) if len(d) else None,
        "coverage": coverage,
        "coverage_detail": cov.summary() if cov is not None else None,
        "deviation": deviation_stats(d) if d_stats is None else d_stats.result(),
        "regions": regions,
        "region_verdicts": user,
        "decision": {
            "counts": class_counts(classes),
            "ambiguous_regions": ambiguous_regions(inp, link_radius_mm=inp.link_radius_mm),
        },
        "uncertainty": uncertainty_summary(inp) if u_summary is None else u_summary.result(),
    }


def deviation_stats(d: NDArray[np.float64]) -> dict[str, Any]:
    """Mean, std, min, max, rms and :data:`PERCENTILES` of the deviations ``d`` (mm; empty: none)."""
    if not len(d):
        return {}
    return {
        "mean_mm": float(d.mean()),
        "std_mm": float(d.std()),
        "min_mm": float(d.min()),
        "max_mm": float(d.max()),
        "rms_mm": float(np.sqrt(np.mean(d * d))),
        "percentiles_mm": {
            f"p{q}": float(v) for q, v in zip(PERCENTILES, np.percentile(d, PERCENTILES), strict=True)
        },
    }


def ambiguous_regions(
    inp: ReportInput, link_radius_mm: float | None = None, max_regions: int = 20
) -> list[dict[str, Any]]:
    """Spatial clusters of the ambiguous points (guarded rule), largest first: centre, the deviation and U
    where the deviation is largest."""
    mask = inp.classes == AMBIGUOUS
    bad, lab = point_clusters(inp.points_mm, mask, link_radius_mm)
    if not len(bad):
        return []
    sizes = np.bincount(lab)
    out: list[dict[str, Any]] = []
    for r in np.argsort(-sizes)[:max_regions]:
        idx = bad[lab == r]
        ext = int(idx[np.argmax(np.abs(inp.deviation_mm[idx]))])
        out.append(
            {
                "name": f"ambiguous-{len(out) + 1}",
                "n_points": int(len(idx)),
                "centre_mm": [round(float(c), 4) for c in inp.points_mm[idx].mean(0)],
                "extreme_mm": round(float(inp.deviation_mm[ext]), 5),
                "extreme_at_mm": [round(float(c), 4) for c in inp.points_mm[ext]],
                "U_mm": round(float(inp.guard_mm[ext]), 5),
                "kind": "excess" if inp.deviation_mm[ext] > 0 else "dent",
            }
        )
    return out


def uncertainty_summary(inp: ReportInput) -> dict[str, Any] | None:
    """The points' uncertainty for report.json: u and U = k u (median, p95, max, mm), the gauging target
    (U at most a quarter of the tolerance band) and the share of points beyond it, and the budget of where u
    came from (:mod:`cell.analysis.uncertainty`); None when the points carry no uncertainty."""
    if inp.uncertainty_mm is None:
        return None
    from cell.analysis.uncertainty import TARGET_SHARE_OF_BAND, stats

    u = np.asarray(inp.uncertainty_mm, dtype=np.float64)
    k = inp.decision.k
    tol = inp.tolerance
    target = TARGET_SHARE_OF_BAND * (tol.upper_mm - tol.lower_mm)
    finite = np.isfinite(u)
    return {
        "k": k,
        "u_mm": stats(u),
        "U_mm": stats(k * u),
        "target_U_mm": round(target, 5),
        "fraction_over_target": round(float(np.mean(~finite | (k * u > target))), 5) if len(u) else None,
        "budget": inp.uncertainty or {},
    }


def _labels(regions: list[dict[str, Any]]) -> list[tuple[str, NDArray[np.float64], str]]:
    """(number, point, hover text) of each out-of-tolerance region, flagged at its extreme point."""
    return [
        (
            str(i + 1),
            np.asarray(r["extreme_at_mm"], np.float64),
            f"{i + 1}: {r['kind']} {r['extreme_mm']:+.3f} mm, {r['n_points']} points",
        )
        for i, r in enumerate(regions)
    ]


def _unmeasured(cov: Coverage | None) -> tuple[NDArray[np.float64] | None, float | None]:
    """The nominal surface samples no point covered (mm) and the samples' spacing (mm), if known."""
    if cov is None or len(cov.covered) == 0:
        return None, None
    spacing = float(np.sqrt(cov.area_mm2 / len(cov.covered)))
    return np.asarray(cov.samples_mm)[~np.asarray(cov.covered)], spacing


def render(doc: dict[str, Any], inp: ReportInput, pictures: bool = True, csv: bool = False) -> str:
    """report.html for the report.json document ``doc`` of ``inp``: pictures, 3D view, page (``csv``: it
    says that deviations.csv is beside it)."""
    from cell.analysis.report_html import render_html
    from cell.analysis.report_uncertainty import uncertainty_html, uncertainty_views

    scale = BandedScale(inp.tolerance.lower_mm, inp.tolerance.upper_mm)
    images: list[dict[str, Any]] = []
    hist = view = None
    u_section = uncertainty_html(doc, uncertainty_views(inp) if pictures else None)
    if pictures and len(inp.points_mm):
        from cell.analysis.pictures import error_map_views, histogram_svg
        from cell.analysis.view3d import figure, view3d_html

        bad = inp.bands.outside(inp.deviation_mm)
        unmeasured, spacing = _unmeasured(inp.coverage)
        labels = _labels(doc["regions"])
        images = error_map_views(
            inp.points_mm,
            inp.deviation_mm,
            scale,
            bad,
            unmeasured_mm=unmeasured,
            unmeasured_spacing_mm=spacing,
            labels=[(t, p) for t, p, _ in labels],
        )
        hist = histogram_svg(inp.deviation_mm, scale)
        view = view3d_html(
            figure(inp.points_mm, inp.deviation_mm, scale, bad, unmeasured_mm=unmeasured, labels=labels)
        )
    return render_html(doc, scale, images, hist, view, csv, u_section)


def write_report(out_dir: Path, inp: ReportInput, pictures: bool = True, csv: bool = False) -> dict[str, Any]:
    """Write report.json, report.html, cloud.ply and (``csv``) deviations.csv into ``out_dir`` as one set
    (a deviations.csv of an earlier report goes when ``csv`` is off); return the json doc. A folder that
    cannot be written is a :class:`cell.errors.ConfigError` naming it."""
    from cell.analysis.report_files import write_file_set

    doc = summarise(inp, _picture_views(inp, pictures))
    writers = {**_page_writers(doc, inp, pictures, csv), "report.json": _json_writer(doc)}
    # an earlier report's print or CSV would not match this report: they go (the print is made from
    # report.html afterwards, :func:`print_report_pdf`)
    write_file_set(
        Path(out_dir), writers, remove=("report.pdf",) if csv else ("report.pdf", "deviations.csv")
    )
    return doc


def write_verdict(out_dir: Path, inp: ReportInput, pictures: bool = True) -> dict[str, Any]:
    """The verdict first: report.json alone into ``out_dir`` (an earlier report's page, cloud, print and CSV
    go: they belong to another verdict); :func:`write_page` writes the rest after it. Returns the doc."""
    from cell.analysis.report_files import write_file_set

    doc = summarise(inp, _picture_views(inp, pictures))
    stale = ("report.html", "cloud.ply", "report.pdf", "deviations.csv")
    write_file_set(Path(out_dir), {"report.json": _json_writer(doc)}, remove=stale)
    return doc


def write_page(
    out_dir: Path, doc: dict[str, Any], inp: ReportInput, pictures: bool = True, csv: bool = False
) -> list[str]:
    """The rest of the report :func:`write_verdict` published ``doc`` of: cloud.ply, report.html and
    (``csv``) deviations.csv, as one set; returns the names written."""
    from cell.analysis.report_files import write_file_set

    writers = _page_writers(doc, inp, pictures, csv)
    write_file_set(Path(out_dir), writers)
    return list(writers)


def _picture_views(inp: ReportInput, pictures: bool) -> list[dict[str, Any]]:
    from cell.analysis.pictures import VIEWS

    if not (pictures and len(inp.points_mm)):
        return []
    return [{"name": n, "elev_deg": el, "azim_deg": az} for n, el, az in VIEWS]


def _json_writer(doc: dict[str, Any]) -> Callable[[Path], Any]:
    return lambda p: p.write_text(json.dumps(doc, indent=2), encoding="utf-8")


def _page_writers(
    doc: dict[str, Any], inp: ReportInput, pictures: bool, csv: bool
) -> dict[str, Callable[[Path], Any]]:
    """cloud.ply, deviations.csv (``csv``) and report.html of the report ``doc`` of ``inp``, as writers."""
    from cell.analysis.report_files import write_csv, write_ply

    page = render(doc, inp, pictures, csv)
    stored = inp.stored or StoredCloud(inp.points_mm, inp.deviation_mm)
    fields = dict(stored.fields)
    if stored.isolated is not None and stored.isolated.any():  # no column: none isolated (2 MB of zeros)
        fields = {"isolated": np.asarray(stored.isolated, bool), **fields}
    return {
        "cloud.ply": lambda p: write_ply(p, stored.points_mm, stored.deviation_mm, fields),
        **({"deviations.csv": lambda p: write_csv(p, inp.points_mm, inp.deviation_mm)} if csv else {}),
        "report.html": lambda p: p.write_text(page, encoding="utf-8"),
    }


def print_report_pdf(out_dir: Path) -> Path:
    """Print ``out_dir``/report.html to report.pdf beside it with headless Chromium (:mod:`cell.chromium`):
    A4, the page's print stylesheet, at most three pages."""
    from cell.chromium import print_pdf

    # "#print": the page leaves its 3D view out (the print shows the static views), so the browser does not
    # spend seconds drawing it in software
    return print_pdf(Path(out_dir) / "report.html", Path(out_dir) / "report.pdf", fragment="print")
