"""The inspection report of an error map: report.json, report.html, cloud.ply (``deviation``), deviations.csv.

The schema of report.json is documented in docs/report-schema.md. Deviations in mm, + outside the material.
Out-of-tolerance points are grouped into regions by a radius graph (cKDTree pairs + connected components).
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cell.analysis.regions import (
    Coverage,
    PointBands,
    Region,
    Tolerance,
    point_bands,
    region_verdicts,
    verdict,
)

__all__ = ["ReportInput", "Tolerance", "out_of_tolerance_regions", "summarise", "write_report"]

SCHEMA_VERSION = 5
PERCENTILES = (1, 5, 25, 50, 75, 95, 99)


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

    @cached_property
    def bands(self) -> PointBands:
        """The band each point is judged by: the report's, or inside user regions with a band of their own
        that band (:func:`cell.analysis.regions.point_bands`)."""
        return point_bands(self.regions, self.points_mm, self.source_face, self.tolerance)


def _default_link_radius(points_mm: NDArray) -> float:
    """3x the cloud's median nearest-neighbour spacing: queried for a random sample of points against the
    whole cloud (a thinned cloud would overstate the spacing), duplicates (zero distances) left out."""
    if len(points_mm) < 2:
        return 0.0
    # an unbalanced tree builds several times faster on millions of points; queries stay exact
    tree = cKDTree(points_mm, balanced_tree=False, compact_nodes=False)
    sample = points_mm[
        np.random.default_rng(0).choice(len(points_mm), min(len(points_mm), 20000), replace=False)
    ]
    d = tree.query(sample, k=8)[0]
    d = np.where(d > 0, d, np.inf).min(axis=1)  # nearest other point, duplicates and self left out
    d = d[np.isfinite(d)]
    return 3.0 * float(np.median(d)) if len(d) else 0.0


def out_of_tolerance_clusters(
    points_mm: NDArray,
    deviation_mm: NDArray,
    band: Tolerance | PointBands,
    link_radius_mm: float | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of the points outside their band (one for all, or one per point) and their cluster label
    (points closer than the link radius, by default :func:`_default_link_radius`, share a cluster)."""
    bad = np.flatnonzero(band.outside(deviation_mm))
    if len(bad) == 0:
        return bad, np.zeros(0, dtype=np.int64)
    radius = _default_link_radius(points_mm) if link_radius_mm is None else link_radius_mm
    pts = points_mm[bad]
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(bad), len(bad)))
    _, lab = connected_components(graph, directed=False)
    return bad, lab.astype(np.int64)


def isolated_out_of_tolerance(
    points_mm: NDArray, deviation_mm: NDArray, band: Tolerance | PointBands, min_points: int
) -> NDArray[np.bool_]:
    """Mask of out-of-tolerance points in clusters of fewer than ``min_points``: isolated outliers (mixed
    pixels at edges, noise spikes) rather than a surface defect, which covers an area."""
    out = np.zeros(len(deviation_mm), dtype=bool)
    bad, lab = out_of_tolerance_clusters(points_mm, deviation_mm, band)
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
        regions.append(
            {
                "name": f"out-of-tolerance-{len(regions) + 1}",
                "verdict": "fail",
                "n_points": int(len(idx)),
                "centre_mm": [round(float(c), 4) for c in pts[idx].mean(0)],
                "extreme_mm": round(float(deviation_mm[bad[ext]]), 5),
                "extreme_at_mm": [round(float(c), 4) for c in pts[ext]],
                "kind": "excess" if deviation_mm[bad[ext]] > 0 else "dent",
            }
        )
    return regions


def summarise(inp: ReportInput, views: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The report.json document (see docs/report-schema.md)."""
    d = inp.deviation_mm
    tol = inp.tolerance
    bands = inp.bands
    inside = ~bands.outside(d)
    stats: dict[str, Any] = {}
    if len(d):
        stats = {
            "mean_mm": float(d.mean()),
            "std_mm": float(d.std()),
            "min_mm": float(d.min()),
            "max_mm": float(d.max()),
            "rms_mm": float(np.sqrt(np.mean(d * d))),
            "percentiles_mm": {
                f"p{q}": float(v) for q, v in zip(PERCENTILES, np.percentile(d, PERCENTILES), strict=True)
            },
        }
    cov = inp.coverage
    coverage = cov.fraction if cov is not None else None
    regions = out_of_tolerance_regions(inp.points_mm, d, bands, link_radius_mm=inp.link_radius_mm)
    user = region_verdicts(inp.regions, inp.points_mm, d, inp.source_face, tol, cov, inp.min_coverage)
    # Any point outside its band or any failing region fails the part; any unmeasured region makes it
    # incomplete.
    overall = verdict(len(d), int((~inside).sum()), coverage, inp.min_coverage)
    region_states = {r["verdict"] for r in user}
    if overall != "no_data" and "fail" in region_states:
        overall = "fail"
    elif overall == "pass" and region_states & {"incomplete", "no_data"}:
        overall = "incomplete"
    if overall in ("pass", "fail") and inp.incomplete_reasons:
        overall = "incomplete"  # a measurement that cannot be trusted neither passes nor fails a part
    return {
        "schema_version": SCHEMA_VERSION,
        "verdict": overall,
        "incomplete_reasons": list(inp.incomplete_reasons),
        "tolerance": {"lower_mm": tol.lower_mm, "upper_mm": tol.upper_mm},
        "n_points": int(len(d)),
        "n_points_input": int(inp.n_points_input),
        "n_out_of_tolerance": int((~inside).sum()),
        "fraction_in_tolerance": float(inside.mean()) if len(d) else None,
        "coverage": coverage,
        "coverage_detail": cov.summary() if cov is not None else None,
        "min_coverage": inp.min_coverage,
        "deviation": stats,
        "regions": regions,
        "region_verdicts": user,
        "excluded": inp.excluded,
        "views": views or [],
        "warnings": list(inp.warnings),
        "alignment": inp.alignment,
        "calibration": inp.calibration,
        "metadata": inp.metadata,
    }


def write_ply(path: Path, points_mm: NDArray, deviation_mm: NDArray) -> None:
    """Binary little-endian PLY with x, y, z (double) and a float ``deviation`` scalar field per vertex."""
    rec = np.empty(len(points_mm), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("deviation", "<f4")])
    rec["x"], rec["y"], rec["z"] = points_mm[:, 0], points_mm[:, 1], points_mm[:, 2]
    rec["deviation"] = deviation_mm
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment units mm; deviation = signed distance to nominal, mm\n"
        f"element vertex {len(rec)}\nproperty double x\nproperty double y\nproperty double z\n"
        "property float deviation\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def write_csv(path: Path, points_mm: NDArray, deviation_mm: NDArray) -> None:
    """deviations.csv: x_mm,y_mm,z_mm,deviation_mm."""
    np.savetxt(
        path,
        np.column_stack([points_mm, deviation_mm]),
        fmt="%.5f",
        delimiter=",",
        header="x_mm,y_mm,z_mm,deviation_mm",
        comments="",
    )


def _pictures(
    points: NDArray, dev: NDArray, tol: Tolerance, bad: NDArray[np.bool_], max_points: int = 100_000
) -> tuple[list, str]:
    """Colour error-map views (base64 PNG, clipped at twice the tolerance) and an SVG histogram; ``bad``:
    the points outside their band, always drawn (cell.analysis.pictures)."""
    from cell.analysis.pictures import error_map_views, histogram_svg

    lim = max(abs(tol.lower_mm), abs(tol.upper_mm)) * 2
    images = error_map_views(points, dev, lim, bad, max_points)
    return images, histogram_svg(dev, tol.lower_mm, tol.upper_mm)


def _percent(fraction: float | None) -> str:
    return "not measured" if fraction is None else f"{100 * fraction:.2f} % of the inspectable surface"


def _alignment_html(al: dict[str, Any] | None) -> str:
    """The alignment used, its correction, residuals per datum and the uncertainty it adds."""
    if not al:
        return "<p>kinematic chain (no alignment recorded)</p>"
    if "error" in al:
        return f"<p><b>{html.escape(al['method'])}</b>: failed: {html.escape(al['error'])}</p>"
    c, u = al.get("correction", {}), al.get("uncertainty_mm")
    unc = (
        "not estimated"
        if not u
        else ", ".join(f"{k} {v:.4f} mm" for k, v in u.items()) + " (1 sigma along the surface normal)"
    )
    rows = "".join(
        f"<tr><td>{html.escape(r['name'])}</td><td>{r['before_mm']:+.4f}</td><td>{r['after_mm']:+.4f}</td>"
        f"<td>{r['spread_mm']:.4f}</td><td>{r['n_points']}</td></tr>"
        for r in al.get("residuals", [])
    )
    table = (
        "<table><tr><th>datum</th><th>before mm</th><th>after mm</th><th>spread mm</th><th>points</th></tr>"
        f"{rows}</table>"
        if rows
        else ""
    )
    rms = "" if al.get("rms_mm") is None else f"; residual rms {al['rms_mm']:.4f} mm"
    return (
        f"<p><b>{html.escape(al['method'])}</b>: moved the measured part by up to "
        f"{c.get('max_mm', 0):.4f} mm "
        f"({c.get('translation_mm', 0):.4f} mm, {c.get('rotation_deg', 0):.4f} deg){rms}; uncertainty added: "
        f"{unc}</p>{table}"
    )


def _calibration_html(cal: dict[str, Any] | None) -> str:
    """The calibration files the run measured with, their age and state."""
    if not cal:
        return "<p>not recorded</p>"
    rows = "".join(
        f"<tr><td>{f['field']}</td><td>{html.escape(f['file'])}</td><td>{f['created_utc']}</td>"
        f"<td>{f['age_days']:.2f}</td><td>{f['made_for_this_config']}</td>"
        f"<td>{html.escape('; '.join(f['problems']) or 'ok')}</td></tr>"
        for f in cal.get("files", [])
    )
    if not rows:
        return f"<p>none: the cell config's nominal geometry (required by the recipe: {cal['required']})</p>"
    return (
        f"<p>required by the recipe: {cal['required']}</p><table><tr><th>calibration</th><th>file</th>"
        "<th>created (UTC)</th><th>age (days)</th><th>made for this cell config</th><th>state</th></tr>"
        f"{rows}</table>"
    )


def _html(doc: dict[str, Any], images: list, hist: str | None) -> str:
    colour = {"pass": "#2a2", "fail": "#c22", "incomplete": "#d80"}.get(doc["verdict"], "#888")
    st = doc["deviation"]
    rows = "".join(
        f"<tr><td>{i + 1}</td><td>{r['kind']}</td><td>{r['n_points']}</td><td>{r['extreme_mm']:+.3f}</td>"
        f"<td>{', '.join(f'{c:.2f}' for c in r['centre_mm'])}</td></tr>"
        for i, r in enumerate(doc["regions"])
    )
    user_rows = "".join(
        f"<tr><td>{r['name']}</td><td>{r['verdict'].upper()}</td><td>{r['n_points']}</td>"
        f"<td>{r['n_out_of_tolerance']}</td><td>{r['tolerance']['lower_mm']:+.3f} .. "
        f"{r['tolerance']['upper_mm']:+.3f}</td><td>{r['coverage']}</td></tr>"
        for r in doc["region_verdicts"]
    )
    pics = "".join(
        f'<figure style="display:inline-block"><img alt="{im["name"]}" '
        f'src="data:image/png;base64,{im["png"]}"><figcaption>{im["name"]}</figcaption></figure>'
        for im in images
    )
    if images:
        from cell.analysis.pictures import colour_bar_html

        tol_d = doc["tolerance"]
        pics += colour_bar_html(2 * max(abs(tol_d["lower_mm"]), abs(tol_d["upper_mm"])))
    hist_html = hist or "<p>(no pictures)</p>"
    stats = "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in st.items())
    meta = json.dumps({"metadata": doc["metadata"], "excluded": doc["excluded"]}, indent=1)
    tol = doc["tolerance"]
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>Inspection report</title>
<style>body{{font-family:sans-serif;margin:2em}} td,th{{border:1px solid #ccc;padding:2px 6px}}
table{{border-collapse:collapse}}
.v{{font-size:2em;color:white;background:{colour};padding:.3em;display:inline-block}}</style>
</head><body><div class="v">{doc["verdict"].upper()}</div>
<p>tolerance {tol["lower_mm"]:+.3f} .. {tol["upper_mm"]:+.3f} mm; {doc["n_points"]} points,
{doc["n_out_of_tolerance"]} out of tolerance; coverage {_percent(doc["coverage"])}</p>
{"".join(f'<p style="color:#d80"><b>incomplete:</b> {html.escape(w)}</p>' for w in doc["incomplete_reasons"])}
{"".join(f'<p style="color:#c22"><b>warning:</b> {html.escape(w)}</p>' for w in doc["warnings"])}
<h2>Alignment</h2>{_alignment_html(doc["alignment"])}<h2>Calibration</h2>{_calibration_html(doc["calibration"])}
<h2>Error map (mm, + outside the material)</h2>{pics}<h2>Histogram</h2>{hist_html}
<h2>Regions</h2><table><tr><th>region</th><th>verdict</th><th>points</th><th>out</th><th>tolerance mm</th>
<th>coverage</th></tr>{user_rows}</table><h2>Out-of-tolerance clusters</h2>
<table><tr><th>#</th><th>kind</th><th>points</th><th>extreme mm</th>
<th>centre mm</th></tr>{rows}</table><h2>Statistics</h2><table>{stats}</table>
<h2>Run</h2><pre>{meta}</pre></body></html>"""


def write_report(out_dir: Path, inp: ReportInput, pictures: bool = True, csv: bool = True) -> dict[str, Any]:
    """Write report.json, report.html, cloud.ply and (``csv``) deviations.csv into ``out_dir``; return the
    json doc."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    images, hist = (
        _pictures(inp.points_mm, inp.deviation_mm, inp.tolerance, inp.bands.outside(inp.deviation_mm))
        if pictures and len(inp.points_mm)
        else ([], None)
    )
    views = [{k: v for k, v in im.items() if k != "png"} for im in images]
    doc = summarise(inp, views)
    (out_dir / "report.json").write_text(json.dumps(doc, indent=2))
    (out_dir / "report.html").write_text(_html(doc, images, hist))
    write_ply(out_dir / "cloud.ply", inp.points_mm, inp.deviation_mm)
    if csv:
        write_csv(out_dir / "deviations.csv", inp.points_mm, inp.deviation_mm)
    return doc
