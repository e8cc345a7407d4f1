"""report.html: the inspection report a metrology reader sees and prints.

Verdict first, with the reason in words; who, what, when and with what (serial, operator, order, recipe and
its hash, cell, software, calibration files and their age); the key figures; the deviation map (an
interactive 3D view on screen, four shaded views with the defects numbered in print and on screen); the
out-of-tolerance regions as a table of callouts; statistics, alignment, calibration. One self-contained file:
pictures and plotly.js are embedded. A print stylesheet lays it out on A4 in at most three pages (verdict and
maps; callouts and statistics; alignment and calibration).

Every string that comes from a user or a file (part, recipe, region and file names, operator, messages) goes
through :func:`e` (HTML) or :func:`css_string` (the printed page footer) and nothing else reaches the page
unescaped. Numbers are formatted by :mod:`cell.analysis.formatting`.
"""

from __future__ import annotations

import re
from pathlib import PurePath
from typing import Any

from cell.analysis import formatting as fmt
from cell.analysis.colour_scale import BandedScale
from cell.analysis.report_style import STYLE
from cell.analysis.report_tables import (
    DASH,
    alignment_html,
    calibration_html,
    callouts_html,
    e,
    measurement_html,
    regions_html,
    stats_html,
)

VERDICT_STYLE = {  # colour, symbol, word
    "pass": ("#1b7f3b", "\u2714", "PASS"),
    "fail": ("#c0172b", "\u2716", "FAIL"),
    "incomplete": ("#b86e00", "!", "INCOMPLETE"),
    "no_data": ("#666666", "\u2013", "NO DATA"),
}


def css_string(value: Any) -> str:
    """A CSS string literal of any value: quotes, backslashes, line breaks and ``<`` escaped (a ``</style>``
    in a part name cannot end the stylesheet)."""
    text = re.sub(r'[\\"<>\n\r\f]', lambda m: f"\\{ord(m.group()):x} ", str(value))
    return f'"{text}"'


def _name(path: Any) -> str:
    return PurePath(str(path)).name if path else DASH


# ---------------------------------------------------------------------------------------------- the verdict
def verdict_reasons(doc: dict[str, Any]) -> list[str]:
    """Why the verdict is what it is, in sentences (plain text, escaped by the caller)."""
    v, tol, dev = doc["verdict"], doc["tolerance"], doc["deviation"]
    band = f"{fmt.signed(tol['lower_mm'])} / {fmt.signed(tol['upper_mm'])} mm"
    if v == "no_data":
        return ["No measured point lies on the part: nothing could be judged."]
    out: list[str] = []
    if v == "incomplete":
        out += list(doc["incomplete_reasons"])
        cov, need = doc.get("coverage"), doc.get("min_coverage")
        if cov is not None and need is not None and cov < need:
            out.append(
                f"Only {fmt.percent(cov)} of the surface was measured; the recipe requires "
                f"{fmt.percent(need)}."
            )
        for r in doc["region_verdicts"]:
            if r["verdict"] in ("incomplete", "no_data"):
                measured = (
                    "not measured" if r["verdict"] == "no_data" else f"covered {fmt.percent(r['coverage'])}"
                )
                out.append(f"Region \u201c{r['name']}\u201d is {measured}: it cannot be judged.")
        if doc["n_out_of_tolerance"]:
            out.append(
                f"{fmt.count(doc['n_out_of_tolerance'])} points lie outside their band; they are shown but "
                "do not make a verdict while the measurement is incomplete."
            )
    if v == "fail":
        regions = doc["regions"]
        if regions:
            worst = max(regions, key=lambda r: abs(r.get("beyond_mm") or abs(r["extreme_mm"])))
            kind = "dent" if worst["kind"] == "dent" else "excess of material"
            out.append(
                f"{fmt.count(doc['n_out_of_tolerance'])} points beyond the tolerance in {len(regions)} "
                f"region{'s' if len(regions) != 1 else ''}. Worst: region {regions.index(worst) + 1}, "
                f"a {kind} "
                f"of {fmt.mm(worst['extreme_mm'])} at {fmt.point(worst['extreme_at_mm'])}"
                + (
                    f", {fmt.mm(abs(worst['beyond_mm']), sign=False)} beyond the limit "
                    f"{fmt.mm(worst['limit_mm'])}."
                    if worst.get("limit_mm") is not None
                    else "."
                )
            )
        for r in doc["region_verdicts"]:
            if r["verdict"] == "fail":
                t = r["tolerance"]
                out.append(
                    f"Region \u201c{r['name']}\u201d fails: {fmt.count(r['n_out_of_tolerance'])} of "
                    f"{fmt.count(r['n_points'])} points outside its band {fmt.signed(t['lower_mm'])} / "
                    f"{fmt.signed(t['upper_mm'])} mm."
                )
    if v == "pass":
        text = (
            f"All {fmt.count(doc['n_points'])} points lie within {band} (largest deviations "
            f"{fmt.mm(dev['min_mm'])} and {fmt.mm(dev['max_mm'])})"
        )
        if doc.get("coverage") is not None:
            need = doc.get("min_coverage")
            text += f"; {fmt.percent(doc['coverage'])} of the surface measured" + (
                f" ({fmt.percent(need)} required)" if need is not None else ""
            )
        out.append(text + ".")
        out += [f"Region \u201c{r['name']}\u201d passes." for r in doc["region_verdicts"]]
    return out


def _verdict_html(doc: dict[str, Any]) -> str:
    colour, symbol, word = VERDICT_STYLE.get(doc["verdict"], VERDICT_STYLE["no_data"])
    reasons = "".join(f"<li>{e(r)}</li>" for r in dict.fromkeys(verdict_reasons(doc)))  # each once
    return (
        f'<section class="verdict" style="--vc:{colour}"><div class="badge" role="status">'
        f'<span class="sym">{symbol}</span><span class="word">{word}</span></div>'
        f'<ul class="why">{reasons}</ul></section>'
    )


# ------------------------------------------------------------------------------------------------- identity
def _calibration_summary(cal: dict[str, Any] | None, geometry: str | None) -> str:
    if not cal:
        return e(geometry) if geometry else "not recorded"
    files = cal.get("files", [])
    if not files:
        return "none: the cell config's nominal geometry"
    oldest = max(f["age_days"] for f in files)
    problems = sum(len(f["problems"]) for f in files)
    state = "all current" if not problems else f"{problems} problem{'s' if problems > 1 else ''} (see below)"
    return f"{len(files)} files, oldest {e(fmt.age(oldest))}; {state}"


def _identity_rows(doc: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, HTML) rows of who, what, when and with what."""
    meta = doc.get("metadata") or {}
    run = meta.get("run") or {}
    ident = run.get("identity") or {}
    recipe, cell = run.get("recipe") or {}, run.get("cell") or {}
    sw = doc.get("software") or {}
    rows = [
        ("Part", e(meta.get("part") or _name(meta.get("nominal")))),
        ("Serial", e(ident.get("serial") or DASH)),
        ("Operator", e(ident.get("operator") or DASH)),
        ("Order", e(ident.get("order") or DASH)),
        ("Inspected", e(fmt.when(run.get("started_utc")))),
        ("Report made", e(fmt.when(doc.get("created_utc")))),
    ]
    if recipe:
        sha = recipe.get("sha256") or ""
        rows.append(
            ("Recipe", f'{e(_name(recipe.get("file")))} <span class="hash">sha256 {e(sha[:12])}</span>')
        )
    nominal = meta.get("cad") or meta.get("nominal")
    if nominal:
        rows.append(("Nominal (CAD)", e(_name(nominal))))
    if meta.get("cloud"):
        rows.append(("Measured cloud", e(_name(meta["cloud"]))))
    if cell:
        sha = (doc.get("calibration") or {}).get("cell_config_sha256") or cell.get("sha256") or ""
        rows.append(("Cell", f'{e(cell.get("name", ""))} <span class="hash">config {e(sha[:12])}</span>'))
    rows.append(("Calibration", _calibration_summary(doc.get("calibration"), meta.get("geometry_source"))))
    al = doc.get("alignment") or ({"method": meta["align"]} if meta.get("align") else None)
    if al:
        rows.append(("Alignment", e(al.get("method", "\u2013"))))
    commit = f' <span class="hash">{e(sw["commit"])}</span>' if sw.get("commit") else ""
    rows.append(("Software", f"{e(sw.get('name', 'inspection-cell'))} {e(sw.get('version', '?'))}{commit}"))
    if run.get("folder"):
        rows.append(("Run", e(run["folder"])))
    return rows


def _identity_html(doc: dict[str, Any]) -> str:
    cells = "".join(f"<div><dt>{label}</dt><dd>{value}</dd></div>" for label, value in _identity_rows(doc))
    return f'<dl class="ident">{cells}</dl>'


def _figures_html(doc: dict[str, Any]) -> str:
    """The key figures as a row of boxes."""
    tol, dev = doc["tolerance"], doc["deviation"]
    n_out = doc["n_out_of_tolerance"]
    boxes = [
        ("tolerance", f"{fmt.signed(tol['lower_mm'])} / {fmt.signed(tol['upper_mm'])}", "mm"),
        ("points judged", fmt.count(doc["n_points"]), f"of {fmt.count(doc['n_points_input'])} measured"),
        ("in tolerance", fmt.percent(doc["fraction_in_tolerance"], 2), f"{fmt.count(n_out)} points beyond"),
        ("coverage", fmt.percent(doc.get("coverage")), f"required {fmt.percent(doc.get('min_coverage'))}"),
        ("min / max", f"{fmt.signed(dev.get('min_mm', 0))} / {fmt.signed(dev.get('max_mm', 0))}", "mm")
        if dev
        else ("min / max", "\u2013", ""),
        ("\u03c3 (std)", fmt.number(dev["std_mm"]) if dev else "\u2013", "mm"),
    ]
    return (
        '<div class="figures">'
        + "".join(
            f'<div class="fig{" bad" if name == "in tolerance" and n_out else ""}">'
            f'<div class="k">{name}</div>'
            f'<div class="v">{value}</div><div class="u">{unit}</div></div>'
            for name, value, unit in boxes
        )
        + "</div>"
    )


# ---------------------------------------------------------------------------------------------- the page
def _maps_html(images: list[dict[str, Any]], scale: BandedScale) -> str:
    if not images:
        return '<p class="none">(no pictures)</p>'
    pics = "".join(
        f'<figure><img alt="{e(im["name"])} view" src="data:image/png;base64,{im["png"]}">'
        f"<figcaption>{e(im['name'])}</figcaption></figure>"
        for im in images
    )
    return f'<div class="views">{pics}</div>{scale.legend_html()}'


def render_html(
    doc: dict[str, Any],
    scale: BandedScale,
    images: list[dict[str, Any]],
    histogram: str | None,
    view3d: str | None,
    csv: bool = False,
    uncertainty: str = "",
) -> str:
    """The whole page from the report.json document and the pictures (already made); ``csv``: a
    deviations.csv is written beside it; ``uncertainty``: the uncertainty section
    (:mod:`cell.analysis.report_uncertainty`)."""
    meta = doc.get("metadata") or {}
    ident = ((meta.get("run") or {}).get("identity")) or {}
    part = meta.get("part") or _name(meta.get("nominal"))
    colour, _, word = VERDICT_STYLE.get(doc["verdict"], VERDICT_STYLE["no_data"])
    footer = " \u00b7 ".join(
        str(x) for x in (part, ident.get("serial"), word, fmt.when(doc.get("created_utc"))) if x
    )
    warnings = "".join(f'<p class="warn"><b>Warning:</b> {e(w)}</p>' for w in doc["warnings"])
    csv_note = ", deviations.csv (the same as text)" if csv else ""
    screen3d = (
        f'<section class="screen-only"><h2>3D deviation map</h2>{view3d}{scale.legend_html(560)}</section>'
        if view3d
        else ""
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width">
<title>{e(word)} \u2013 {e(part)} \u2013 inspection report</title>
<style>{STYLE}
@page {{ @bottom-left {{ content: {css_string(footer)}; }} }}
</style></head><body>
<header class="top"><div><div class="kicker">Surface inspection report</div><h1>{e(part)}</h1></div>
<div class="serial">{e(ident.get("serial") or "")}</div></header>
{_verdict_html(doc)}
{warnings}
{_identity_html(doc)}
{_figures_html(doc)}
{screen3d}
<section class="maps"><h2>Deviation map <span class="sub">mm, + outside the material; numbers: the regions
below</span></h2>{_maps_html(images, scale)}</section>
<section class="callouts-sec"><h2>Beyond tolerance</h2>{callouts_html(doc)}{regions_html(doc)}</section>
<section class="stats-sec"><h2>Statistics</h2><div class="two">{histogram or ""}{stats_html(doc)}</div>
</section>
<section class="unc-sec"><h2>Uncertainty and decision <span class="sub">U = k u, mm, along the
normal; purple: ambiguous</span></h2>{uncertainty}</section>
<section class="details"><h2>Alignment</h2>{alignment_html(doc.get("alignment"), doc["warnings"])}
<h2>Calibration</h2>{calibration_html(doc.get("calibration"), meta.get("geometry_source"))}
<h2>Measurement</h2>{measurement_html(doc)}
<p class="files">Files beside this report: report.json (schema version {doc["schema_version"]}, every figure
above), cloud.ply (every point with its deviation and uncertainty){csv_note}.</p>
</section>
</body></html>"""
