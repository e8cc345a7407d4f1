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

import html
import re
from pathlib import PurePath
from typing import Any

from cell.analysis import formatting as fmt
from cell.analysis.colour_scale import BandedScale

VERDICT_STYLE = {  # colour, symbol, word
    "pass": ("#1b7f3b", "\u2714", "PASS"),
    "fail": ("#c0172b", "\u2716", "FAIL"),
    "incomplete": ("#b86e00", "!", "INCOMPLETE"),
    "no_data": ("#666666", "\u2013", "NO DATA"),
}


DASH = "\u2013"  # the sign for a value not known or not applicable


def e(value: Any) -> str:
    """HTML-escaped text of any value (quotes too: safe in attributes)."""
    return html.escape(str(value), quote=True)


def css_string(value: Any) -> str:
    """A CSS string literal of any value: quotes, backslashes, line breaks and ``<`` escaped (a ``</style>``
    in a part name cannot end the stylesheet)."""
    text = re.sub(r'[\\"<>\n\r\f]', lambda m: f"\\{ord(m.group()):x} ", str(value))
    return f'"{text}"'


def _name(path: Any) -> str:
    return PurePath(str(path)).name if path else "\u2013"


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
    reasons = "".join(f"<li>{e(r)}</li>" for r in verdict_reasons(doc))
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
        ("Serial", e(ident.get("serial") or "\u2013")),
        ("Operator", e(ident.get("operator") or "\u2013")),
        ("Order", e(ident.get("order") or "\u2013")),
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


# ----------------------------------------------------------------------------------------------- the tables
def _callouts_html(doc: dict[str, Any]) -> str:
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


def _regions_html(doc: dict[str, Any]) -> str:
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


def _stats_html(doc: dict[str, Any]) -> str:
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


def _alignment_html(al: dict[str, Any] | None) -> str:
    """The alignment used, its correction, residuals per datum and the uncertainty it adds."""
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
    warn = "".join(f'<p class="warn">{e(w)}</p>' for w in al.get("warnings", []))
    return (
        f"<p><b>{e(al['method'])}</b>: moved the measured part by up to "
        f"{fmt.number(c.get('max_mm', 0), 3)} mm ({fmt.number(c.get('translation_mm', 0), 3)} mm, "
        f"{fmt.number(c.get('rotation_deg', 0), 3)}\u00b0){rms}; uncertainty added: {unc}.</p>{warn}{table}"
    )


def _calibration_html(cal: dict[str, Any] | None, geometry: str | None) -> str:
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


def _measurement_html(doc: dict[str, Any]) -> str:
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
) -> str:
    """The whole page from the report.json document and the pictures (already made)."""
    meta = doc.get("metadata") or {}
    ident = ((meta.get("run") or {}).get("identity")) or {}
    part = meta.get("part") or _name(meta.get("nominal"))
    colour, _, word = VERDICT_STYLE.get(doc["verdict"], VERDICT_STYLE["no_data"])
    footer = " \u00b7 ".join(
        str(x) for x in (part, ident.get("serial"), word, fmt.when(doc.get("created_utc"))) if x
    )
    warnings = "".join(f'<p class="warn"><b>Warning:</b> {e(w)}</p>' for w in doc["warnings"])
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
<section class="callouts-sec"><h2>Beyond tolerance</h2>{_callouts_html(doc)}{_regions_html(doc)}</section>
<section class="stats-sec"><h2>Statistics</h2><div class="two">{histogram or ""}{_stats_html(doc)}</div>
</section>
<section class="details"><h2>Alignment</h2>{_alignment_html(doc.get("alignment"))}
<h2>Calibration</h2>{_calibration_html(doc.get("calibration"), meta.get("geometry_source"))}
<h2>Measurement</h2>{_measurement_html(doc)}
<p class="files">Files beside this report: report.json (schema version {doc["schema_version"]}, every figure
above), cloud.ply (every point with its deviation).</p></section>
</body></html>"""


STYLE = """
:root { --ink:#1d1d1f; --muted:#6b6b70; --rule:#d6d6da; --soft:#f4f4f6; }
* { box-sizing: border-box; }
body { font: 14px/1.4 "DejaVu Sans", "Segoe UI", Helvetica, Arial, sans-serif; color: var(--ink);
  margin: 0 auto; max-width: 1100px; padding: 24px 28px 40px; }
h1 { font-size: 26px; margin: 2px 0 0; }
h2 { font-size: 16px; margin: 22px 0 8px; padding-bottom: 3px; border-bottom: 2px solid var(--ink); }
h2 .sub { font-size: 12px; font-weight: normal; color: var(--muted); }
h3 { font-size: 14px; margin: 14px 0 6px; }
.top { display: flex; justify-content: space-between; align-items: flex-end;
  border-bottom: 1px solid var(--rule);
  padding-bottom: 8px; }
.kicker { text-transform: uppercase; letter-spacing: .08em; font-size: 11px; color: var(--muted); }
.serial { font: 600 18px "DejaVu Sans Mono", Consolas, monospace; }
.verdict { display: flex; gap: 18px; align-items: center; margin: 14px 0; border: 2px solid var(--vc);
  border-radius: 6px; overflow: hidden; }
.badge { background: var(--vc); color: #fff; padding: 12px 22px; display: flex; align-items: center;
  gap: 10px;
  min-width: 230px; align-self: stretch; }
.badge .sym { font-size: 34px; line-height: 1; }
.badge .word { font-size: 30px; font-weight: 700; letter-spacing: .04em; }
.why { margin: 8px 12px 8px 0; padding-left: 18px; }
.why li { margin: 2px 0; }
.warn { color: #9a3b00; }
.ok { color: #1b7f3b; }
.ident { display: grid; grid-template-columns: repeat(3, 1fr); gap: 2px 18px; margin: 10px 0; }
.ident div { display: flex; gap: 8px; border-bottom: 1px dotted var(--rule); padding: 2px 0; }
.ident dt { color: var(--muted); min-width: 92px; }
.ident dd { margin: 0; font-weight: 600; overflow-wrap: anywhere; }
.hash { font: 11px "DejaVu Sans Mono", monospace; color: var(--muted); font-weight: normal; }
.figures { display: grid; grid-template-columns: repeat(6, 1fr); gap: 8px; margin: 12px 0; }
.fig { background: var(--soft); border-radius: 5px; padding: 6px 10px; }
.fig .k { font-size: 11px; text-transform: uppercase; letter-spacing: .05em; color: var(--muted); }
.fig .v { font-size: 18px; font-weight: 700; white-space: nowrap; }
.fig .u { font-size: 11px; color: var(--muted); }
.fig.bad .v { color: #c0172b; }
.view3d { height: 560px; border: 1px solid var(--rule); border-radius: 4px; color: var(--muted);
  padding: 4px; }
.views { display: grid; grid-template-columns: repeat(2, 1fr); gap: 8px; }
.views figure { margin: 0; border: 1px solid var(--rule); border-radius: 4px; text-align: center; }
.views img { width: 100%; height: auto; display: block; }
.views figcaption { font-size: 12px; color: var(--muted); padding: 2px; }
.legend { margin: 10px 0 4px; font-size: 12px; }
.legend .bar { position: relative; height: 16px; border: 1px solid #888; }
.legend .tick { position: absolute; top: -4px; bottom: -4px; width: 0; border-left: 2px solid #111; }
.legend .tick.ref { border-left: 1px dashed #555; top: 0; bottom: 0; }
.legend .ticklabel { position: absolute; top: 18px; transform: translateX(-50%); font-weight: 600; }
.legend .ticklabel.ref { font-weight: normal; color: var(--muted); }
.legend .ends { display: flex; justify-content: space-between; margin-top: 18px; color: var(--muted); }
.legend .keys { display: flex; gap: 16px; margin-top: 4px; flex-wrap: wrap; }
.legend .sw { display: inline-block; width: 14px; height: 10px; border: 1px solid #888; margin-right: 5px;
  vertical-align: -1px; }
.legend .sw.hatch { background: repeating-linear-gradient(45deg, #696969 0 2px, #ececec 2px 5px); }
table { border-collapse: collapse; margin: 4px 0; font-size: 13px; }
th, td { border-bottom: 1px solid var(--rule); padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: var(--soft); font-weight: 600; font-size: 12px; }
td.r, th.r { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
.flag { display: inline-block; min-width: 22px; padding: 0 5px; border: 2px solid #111; border-radius: 6px;
  text-align: center; font-weight: 700; }
tr.dent td:nth-child(3) { color: #1d4fb0; }
tr.excess td:nth-child(3) { color: #b01010; }
.vd.pass { color: #1b7f3b; font-weight: 700; } .vd.fail { color: #c0172b; font-weight: 700; }
.vd.incomplete, .vd.no_data { color: #b86e00; font-weight: 700; }
.two { display: flex; gap: 22px; align-items: flex-start; flex-wrap: wrap; }
.hist { max-width: 100%; height: auto; }
.none { color: var(--muted); }
.files { color: var(--muted); font-size: 12px; margin-top: 16px; }
@page { size: A4; margin: 11mm 11mm 13mm;
  @bottom-right { content: "page " counter(page) " of " counter(pages); font: 9px sans-serif; color: #666; }
  @bottom-left { font: 9px sans-serif; color: #666; } }
@media print {
  body { font-size: 9.5px; max-width: none; padding: 0; }
  .screen-only { display: none; }
  .top { padding-bottom: 4px; } h1 { font-size: 19px; } .serial { font-size: 15px; }
  h2 { font-size: 12.5px; margin: 9px 0 4px; }
  h3 { font-size: 11px; margin: 8px 0 4px; }
  .verdict { margin: 6px 0; } .badge { padding: 6px 14px; min-width: 170px; }
  .badge .sym { font-size: 24px; } .badge .word { font-size: 22px; }
  .why { margin: 5px 10px 5px 0; }
  .ident { margin: 4px 0; gap: 0 12px; } .ident dt { min-width: 70px; } .ident div { padding: 1px 0; }
  .hash { font-size: 8.5px; }
  .figures { margin: 6px 0; gap: 4px; } .fig { padding: 3px 7px; }
  .fig .k { font-size: 7.5px; } .fig .v { font-size: 12.5px; } .fig .u { font-size: 8px; }
  .maps { break-inside: avoid; }
  .views { grid-template-columns: repeat(2, 78mm); justify-content: center; gap: 3mm; }
  .views figcaption { font-size: 9px; padding: 0; }
  .legend { width: 120mm !important; margin: 5px auto 0; font-size: 9px; }
  table { font-size: 9.5px; } th { font-size: 8.5px; } th, td { padding: 1.5px 6px; }
  .callouts-sec { break-before: page; }
  .stats-sec, table { break-inside: avoid; }
  .hist { width: 112mm; height: auto; }
  * { -webkit-print-color-adjust: exact; print-color-adjust: exact; }
}
"""
