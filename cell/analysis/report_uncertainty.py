"""The report's uncertainty section: the map of U = k u (like the deviation views), the decision rule and how
many points each class holds, the ambiguous areas and the uncertainty budget (docs/uncertainty.md).

Every string from a file goes through :func:`cell.analysis.report_tables.e`; numbers through
:mod:`cell.analysis.formatting`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cell.analysis import formatting as fmt
from cell.analysis.colour_scale import UncertaintyScale
from cell.analysis.decision import AMBIGUOUS, NONCONFORM
from cell.analysis.report_tables import DASH, e

RULE_TEXT = {
    "simple": "simple: every deviation against its band, as if exact (U is shown, not used)",
    "guarded": "guarded (ISO 14253-1): conforms within the band shrunk by U, does not beyond the band "
    "widened by U, ambiguous in between",
}


def uncertainty_views(inp: Any) -> tuple[list[dict[str, Any]], UncertaintyScale] | None:
    """The four standard views coloured by U (ambiguous points purple), or None without uncertainties.
    ``inp``: the :class:`cell.analysis.report.ReportInput`."""
    if inp.uncertainty_mm is None or not len(inp.points_mm):
        return None
    from cell.analysis.pictures import error_map_views
    from cell.analysis.uncertainty import TARGET_SHARE_OF_BAND

    tol = inp.tolerance
    scale = UncertaintyScale(TARGET_SHARE_OF_BAND * (tol.upper_mm - tol.lower_mm))
    U = inp.decision.k * np.asarray(inp.uncertainty_mm, dtype=np.float64)
    ambiguous = inp.classes == AMBIGUOUS
    colours = scale.rgb(U, ambiguous)
    images = error_map_views(
        inp.points_mm,
        inp.deviation_mm,
        None,  # the colours are given
        ambiguous | (inp.classes == NONCONFORM),
        colours=colours,
        width_px=360,
    )
    return images, scale


def _stat(s: dict[str, Any] | None, key: str) -> str:
    v = (s or {}).get(key)
    return DASH if v is None else fmt.number(v)


def uncertainty_html(doc: dict[str, Any], views: tuple[list[dict[str, Any]], UncertaintyScale] | None) -> str:
    """The section's HTML from report.json's ``decision`` and ``uncertainty`` and the U views."""
    dec, unc = doc.get("decision") or {}, doc.get("uncertainty")
    counts = dec.get("counts", {})
    rule = dec.get("rule", "simple")
    guard = f"; k = {dec.get('k', 2.0):g}; ambiguous points: {e(dec.get('ambiguous'))}"
    head = f"<p>Decision rule: <b>{e(RULE_TEXT.get(rule, rule))}</b>{guard if rule == 'guarded' else ''}.</p>"
    classes = (
        "<table><tr><th>class</th><th class='r'>points</th></tr>"
        + "".join(
            f"<tr><td>{label}</td><td class='r'>{fmt.count(counts.get(key, 0))}</td></tr>"
            for key, label in (
                ("conform", "conform"),
                ("ambiguous", "ambiguous"),
                ("nonconform", "do not conform"),
            )
        )
        + "</table>"
    )
    if unc is None:
        return head + classes + '<p class="none">The points carry no uncertainty (measured elsewhere).</p>'
    budget = unc.get("budget") or {}
    parts = [
        ("u, total", unc.get("u_mm")),
        ("decode (noise, quantisation, calibration)", budget.get("decode_mm")),
        ("views' poses, after the alignment", budget.get("pose_mm")),
    ]
    rows = "".join(
        f"<tr><td>{label}</td><td class='r'>{_stat(s, 'median')}</td><td class='r'>{_stat(s, 'p95')}</td>"
        f"<td class='r'>{_stat(s, 'max')}</td></tr>"
        for label, s in parts
    )
    align = budget.get("alignment_mm")
    align_text = DASH if align is None else fmt.number(align)
    rows += f"<tr><td>alignment (common)</td><td class='r' colspan='3'>{align_text}</td></tr>"
    table = (
        "<table><tr><th>standard uncertainty, mm</th><th class='r'>median</th><th class='r'>p95</th>"
        f"<th class='r'>max</th></tr>{rows}</table>"
    )
    target = (
        f"<p>U = {unc.get('k', 2.0):g} u: median {_stat(unc.get('U_mm'), 'median')} mm, p95 "
        f"{_stat(unc.get('U_mm'), 'p95')} mm; target U &le; {fmt.number(unc['target_U_mm'])} mm (a "
        f"quarter of the band), missed by {fmt.percent(unc.get('fraction_over_target'))} of the points. "
        f"Calibration residual: {e(budget.get('calibration', DASH))}. Views' poses: "
        f"{e(budget.get('poses') or DASH)}.</p>"
    )
    amb = dec.get("ambiguous_regions") or []
    amb_html = ""
    if amb:
        amb_rows = "".join(
            f"<tr><td>{e(r['name'])}</td><td class='r'>{fmt.count(r['n_points'])}</td>"
            f"<td class='r'>{fmt.mm(r['extreme_mm'])}</td><td class='r'>{fmt.number(r['U_mm'])}</td>"
            f"<td>{e(fmt.point(r['extreme_at_mm']))}</td></tr>"
            for r in amb[:8]
        )
        amb_html = (
            "<table><tr><th>ambiguous area</th><th class='r'>points</th><th class='r'>deviation</th>"
            f"<th class='r'>U there</th><th>at</th></tr>{amb_rows}</table>"
        )
    pics = ""
    if views is not None:
        images, scale = views
        pics = (
            '<div class="views uviews">'
            + "".join(
                f'<figure><img alt="{e(im["name"])} view of U" src="data:image/png;base64,{im["png"]}">'
                f"<figcaption>{e(im['name'])}</figcaption></figure>"
                for im in images
            )
            + f"</div>{scale.legend_html()}"
        )
    return head + f'<div class="two">{classes}{table}</div>' + target + amb_html + pics
