"""The tables of the report page (cell.analysis.report_html): the out-of-tolerance regions as numbered
callouts, the recipe's regions, the statistics, the alignment, the calibration files and how the points were
measured. User strings through :func:`cell.analysis.report_html.e`; numbers through
:mod:`cell.analysis.formatting`."""

from __future__ import annotations

import html
from typing import Any

from cell.analysis import formatting as fmt

DASH = "\u2013"


def e(value: Any) -> str:
    """HTML-escaped text of any value (quotes too: safe in attributes)."""
    return html.escape(str(value), quote=True)


def callouts_html(doc: dict[str, Any]) -> str:
    regions = doc["regions"]
    if not regions:
        return '<p class="none">No point lies beyond its tolerance.</p>'
    rows = "".join(
        f'<tr class="{r["kind"]}"><td class="num"><span class="flag">{i + 1}</span></td>'
        f"<td>{'dent (below)' if r['kind'] == 'dent' else 'excess (above)'}</td>"
        f'<td class="r"><b>{fmt.signed(r["extreme_mm"])}</b></td>'
        f'<td class="r">{fmt.signed(r["limit_mm"]) if r.get("limit_mm") is not None else DASH}</td>'
        f'<td class="r">{fmt.number(abs(r["beyond_mm"])) if r.get("beyond_mm") is not None else DASH}</td>'
        f"<td>{fmt.point(r['extreme_at_mm'])}</td><td>{fmt.point(r['centre_mm'])}</td>"
        f'<td class="r">{fmt.count(r["n_points"])}</td></tr>'
        for i, r in enumerate(regions)
    )
    return (
        '<table class="callouts"><thead><tr><th>#</th><th>kind</th><th>worst mm</th><th>limit mm</th>'
        "<th>beyond mm</th><th>worst at (x, y, z) mm</th><th>centre (x, y, z) mm</th><th>points</th></tr>"
        f"</thead><tbody>{rows}</tbody></table>"
    )


def regions_html(doc: dict[str, Any]) -> str:
    user = doc["region_verdicts"]
    if not user:
        return ""
    rows = "".join(
        f'<tr><td>{e(r["name"])}</td><td class="vd {e(r["verdict"])}">{e(r["verdict"].upper())}</td>'
        f"<td>{fmt.signed(r['tolerance']['lower_mm'])} / {fmt.signed(r['tolerance']['upper_mm'])}</td>"
        f'<td class="r">{fmt.count(r["n_points"])}</td>'
        f'<td class="r">{fmt.count(r["n_out_of_tolerance"])}</td>'
        f'<td class="r">{fmt.signed(r["min_mm"]) if r["min_mm"] is not None else DASH}</td>'
        f'<td class="r">{fmt.signed(r["max_mm"]) if r["max_mm"] is not None else DASH}</td>'
        f'<td class="r">{fmt.percent(r["coverage"])}</td></tr>'
        for r in user
    )
    return (
        "<h3>Regions of the recipe</h3><table><thead><tr><th>region</th><th>verdict</th><th>band mm</th>"
        "<th>points</th><th>beyond</th><th>min mm</th><th>max mm</th><th>coverage</th></tr></thead>"
        f"<tbody>{rows}</tbody></table>"
    )


def stats_html(doc: dict[str, Any]) -> str:
    st = doc["deviation"]
    if not st:
        return '<p class="none">No points.</p>'
    rows = [
        ("mean", fmt.signed(st["mean_mm"])),
        ("\u03c3 (standard deviation)", fmt.number(st["std_mm"])),
        ("rms", fmt.number(st["rms_mm"])),
        ("min", fmt.signed(st["min_mm"])),
        ("max", fmt.signed(st["max_mm"])),
        *(
            (f"P{k[1:]} ({k[1:]}{fmt.THIN}% of the points below)", fmt.signed(v))
            for k, v in st["percentiles_mm"].items()
        ),
    ]
    return (
        '<table class="stats"><thead><tr><th>deviation</th><th class="r">mm</th></tr></thead><tbody>'
        + "".join(f'<tr><td>{k}</td><td class="r">{v}</td></tr>' for k, v in rows)
        + "</tbody></table>"
    )


def alignment_html(al: dict[str, Any] | None, shown: list[str]) -> str:
    """The alignment used, its correction, residuals per datum and the uncertainty it adds (its warnings
    unless already ``shown`` at the top)."""
    if not al:
        return "<p>Kinematic chain (no alignment recorded).</p>"
    if "error" in al:
        return f'<p class="warn"><b>{e(al["method"])}</b> failed: {e(al["error"])}</p>'
    c, u = al.get("correction", {}), al.get("uncertainty_mm")
    unc = (
        "not estimated"
        if not u
        else ", ".join(f"{e(k)} {fmt.number(v, 4)} mm" for k, v in u.items() if v is not None)
        + " (1\u03c3 along the surface normal)"
    )
    rows = "".join(
        f'<tr><td>{e(r["name"])}</td><td class="r">{fmt.signed(r["before_mm"], 4)}</td>'
        f'<td class="r">{fmt.signed(r["after_mm"], 4)}</td><td class="r">{fmt.number(r["spread_mm"], 4)}</td>'
        f'<td class="r">{fmt.count(r["n_points"])}</td></tr>'
        for r in al.get("residuals", [])
    )
    table = (
        "<table><thead><tr><th>datum</th><th>before mm</th><th>after mm</th><th>spread mm</th>"
        f"<th>points</th></tr></thead><tbody>{rows}</tbody></table>"
        if rows
        else ""
    )
    rms = "" if al.get("rms_mm") is None else f"; residual rms {fmt.number(al['rms_mm'], 4)} mm"
    warn = "".join(f'<p class="warn">{e(w)}</p>' for w in al.get("warnings", []) if w not in shown)
    return (
        f"<p><b>{e(al['method'])}</b>: moved the measured part by up to "
        f"{fmt.number(c.get('max_mm', 0), 3)} mm ({fmt.number(c.get('translation_mm', 0), 3)} mm, "
        f"{fmt.number(c.get('rotation_deg', 0), 3)}\u00b0){rms}; uncertainty added: {unc}.</p>{warn}{table}"
    )


def calibration_html(cal: dict[str, Any] | None, geometry: str | None) -> str:
    """The calibration files the run measured with, their age and state."""
    if not cal:
        return f"<p>{e(geometry) if geometry else 'Not recorded.'}</p>"
    rows = "".join(
        f"<tr><td>{e(f['field'])}</td><td>{e(f['file'])}</td><td>{e(fmt.when(f['created_utc']))}</td>"
        f'<td class="r">{e(fmt.age(f["age_days"]))}</td>'
        f"<td>{ {True: 'yes', False: 'no', None: 'not recorded'}[f['made_for_this_config']] }</td>"
        f'<td class="{"ok" if not f["problems"] else "warn"}">{e("; ".join(f["problems"]) or "ok")}</td></tr>'
        for f in cal.get("files", [])
    )
    required = "required by the recipe" if cal.get("required") else "not required by the recipe"
    if not rows:
        return f"<p>None: the cell config's nominal geometry ({required}).</p>"
    return (
        f"<p>Calibration {required}.</p><table><thead><tr><th>calibration</th><th>file</th><th>created</th>"
        "<th>age</th><th>made for this cell config</th><th>state</th></tr></thead>"
        f"<tbody>{rows}</tbody></table>"
    )


def measurement_html(doc: dict[str, Any]) -> str:
    """How the points were obtained and what was left out."""
    meta = doc.get("metadata") or {}
    items = []
    reg, ev = meta.get("registration") or {}, meta.get("evaluation") or {}
    if meta.get("views"):
        items.append(f"{len(meta['views'])} views planned")
    if reg.get("views") is not None:
        items.append(f"{reg['views']} views merged into {fmt.count(reg.get('n_points'))} points")
    ref = reg.get("refinement") or {}
    if ref.get("rms_after_mm") is not None:
        items.append(
            f"views refined against each other: rms {fmt.number(ref['rms_before_mm'], 4)} \u2192 "
            f"{fmt.number(ref['rms_after_mm'], 4)} mm"
        )
    if ev.get("Q") is not None:
        items.append(f"measurement quality Q {e(ev['Q'])} (set point {e(ev.get('setpoint', DASH))})")
    if meta.get("method"):
        items.append(e(meta["method"]))
    excluded = "".join(
        f'<tr><td>{e(k.replace("_", " "))}</td><td class="r">{fmt.count(v)}</td></tr>'
        for k, v in (doc.get("excluded") or {}).items()
    )
    return ("<ul>" + "".join(f"<li>{i}</li>" for i in items) + "</ul>" if items else "") + (
        f"<table><thead><tr><th>left out</th><th>points</th></tr></thead><tbody>{excluded}</tbody></table>"
        if excluded
        else ""
    )
