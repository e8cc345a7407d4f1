"""The verdict page's content from a finished run's ``results/report.json`` (docs/report-schema.md): the
verdict, and the reasons in an operator's words. The report itself (report.html) is the report module's; the
station links and embeds it, it does not rebuild it."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class Defect:
    """The largest out-of-tolerance region: dent or excess, its extreme deviation (mm), where (part frame,
    mm), how many points, and the recipe region it lies in (a box region holding its centre), if any."""

    kind: str
    value_mm: float
    at_mm: list[float]
    n_points: int
    name: str
    region: str | None


@dataclass
class Verdict:
    """What the verdict page shows: ``verdict`` (pass, fail, incomplete, no_data) and why."""

    verdict: str
    reasons: list[str] = field(default_factory=list)
    defect: Defect | None = None
    figures: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def _region_of(centre: list[float], region_boxes: Sequence[tuple[str, list[list[float]]]]) -> str | None:
    for name, (lo, hi) in region_boxes:
        if all(a <= c <= b for a, c, b in zip(lo, centre, hi)):
            return name
    return None


def read_verdict(run_dir: Path, region_boxes: Sequence[tuple[str, list[list[float]]]] = ()) -> Verdict | None:
    """The verdict of the run in ``run_dir`` with its reasons, or None when it has no report (yet).
    ``region_boxes`` are the recipe's box regions (name, [lo, hi] in the part frame, mm)."""
    path = run_dir / "results" / "report.json"
    if not path.is_file():
        return None
    doc = json.loads(path.read_text())
    tol = doc.get("tolerance") or {}
    dev = doc.get("deviation") or {}
    out = Verdict(str(doc.get("verdict")), warnings=list(doc.get("warnings") or []))
    out.figures = {
        "tolerance": f"{tol.get('lower_mm', 0):+.3f} / {tol.get('upper_mm', 0):+.3f} mm",
        "points": doc.get("n_points"),
        "coverage": doc.get("coverage"),
        "min_coverage": doc.get("min_coverage"),
        "mean_mm": dev.get("mean_mm"),
        "min_mm": dev.get("min_mm"),
        "max_mm": dev.get("max_mm"),
        "out_of_tolerance": doc.get("n_out_of_tolerance"),
    }
    regions = doc.get("regions") or []
    if regions:
        r = regions[0]
        out.defect = Defect(
            kind=r.get("kind", "?"),
            value_mm=float(r["extreme_mm"]),
            at_mm=[float(v) for v in r.get("extreme_at_mm") or r.get("centre_mm")],
            n_points=int(r.get("n_points", 0)),
            name=r.get("name", ""),
            region=_region_of(r.get("centre_mm", [0, 0, 0]), region_boxes),
        )
        more = f" (and {len(regions) - 1} more out-of-tolerance region(s))" if len(regions) > 1 else ""
        out.reasons.append(
            f"{out.defect.kind} of {out.defect.value_mm:+.3f} mm, beyond the tolerance "
            f"{out.figures['tolerance']}{more}"
        )
    for rv in doc.get("region_verdicts") or []:
        if rv.get("verdict") in ("fail", "incomplete", "no_data"):
            low, high = rv.get("min_mm"), rv.get("max_mm")
            span = f": {low:+.3f} to {high:+.3f} mm" if low is not None and high is not None else ""
            said = {"fail": "failed", "incomplete": "is incomplete", "no_data": "has no points"}[
                rv["verdict"]
            ]
            out.reasons.append(f"region '{rv.get('name')}' {said}{span}")
    out.reasons.extend(doc.get("incomplete_reasons") or [])
    coverage, needed = doc.get("coverage"), doc.get("min_coverage")
    if coverage is not None and needed is not None and coverage < needed:
        out.reasons.append(f"coverage {100 * coverage:.1f} % is below the required {100 * needed:.1f} %")
    if out.verdict == "no_data":
        out.reasons.append("no measured point: nothing to judge")
    return out
