"""The acceptance test's report page (HTML) and its JSON. Every string that comes from a file or a person
(cell name, labels, serials, errors) is escaped."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from html import escape
from pathlib import Path

from cell.runs import write_atomic
from cell.verification.certificate import Certificate
from cell.verification.procedure import AcceptanceResult

NAMES = {
    "PF": "probing error, form",
    "PS": "probing error, size",
    "SD": "sphere-spacing error",
    "F": "flatness measurement error",
}


def _mm(v: float | None, signed: bool = True) -> str:
    """Micrometres; ranges (PF, F) unsigned, errors (PS, SD) signed."""
    return "&ndash;" if v is None else f"{v * 1000:+.1f}" if signed else f"{v * 1000:.1f}"


def _ok(v: bool | None) -> str:
    return {True: '<b class="pass">pass</b>', False: '<b class="fail">FAIL</b>', None: "not measured"}[v]


def write_json(path: Path, result: AcceptanceResult, certificate: Certificate, note: str) -> None:
    doc = {
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "note": note,
        **result.to_dict(),
        "certificate": certificate.model_dump(mode="json"),
    }
    write_atomic(path, json.dumps(doc, indent=2).encode())


def write_html(path: Path, result: AcceptanceResult, certificate: Certificate, note: str) -> None:
    """One page: verdict, the four figures against their MPEs, every position, the artefacts and the
    geometry the measurement rests on. Values in micrometres."""
    rows = "".join(
        f"<tr><td>{k} ({NAMES[k]})</td><td>{_mm(result.figures_mm.get(k), k in ('PS', 'SD'))}</td>"
        f"<td>{result.mpe_mm[k] * 1000:.1f}</td><td>{_ok(result.passed.get(k))}</td></tr>"
        for k in NAMES
    )

    def rms(values: list[float]) -> str:
        return " / ".join(f"{v * 1000:.1f}" for v in values)

    pos_rows = "".join(
        f"<tr><td>{escape(r.label)}</td><td>{' / '.join(_mm(v, False) for v in r.pf_mm) or '&ndash;'}</td>"
        f"<td>{' / '.join(_mm(v) for v in r.ps_mm) or '&ndash;'}</td><td>{_mm(r.sd_mm)}</td>"
        f"<td>{_mm(r.f_mm, False)}</td><td>{rms(r.rms_mm)}</td><td>{r.n_points}</td>"
        f"<td>{r.excluded_points}</td>"
        f"<td>{escape(r.error or '')}</td></tr>"
        for r in result.positions
    )
    c = certificate
    arts = [
        (
            "sphere",
            c.sphere.serial,
            f"diameter {c.sphere.diameter_mm:.4f} mm, form {c.sphere.form_mm * 1000:.1f} um",
            c.sphere,
        ),
        (
            "ball bar",
            c.ball_bar.serial,
            f"centre distance {c.ball_bar.centre_distance_mm:.4f} mm, spheres "
            + " / ".join(f"{d:.4f}" for d in c.ball_bar.sphere_diameters_mm)
            + " mm",
            c.ball_bar,
        ),
        (
            "plane",
            c.plane.serial,
            f"{c.plane.length_mm:g} x {c.plane.width_mm:g} mm, flatness {c.plane.flatness_mm * 1000:.1f} um",
            c.plane,
        ),
    ]
    art_rows = "".join(
        f"<tr><td>{name}</td><td>{escape(serial)}</td><td>{escape(text)}</td><td>{escape(a.laboratory)}</td>"
        f"<td>{escape(a.date)}</td><td>{a.uncertainty_mm * 1000:.1f}</td></tr>"
        for name, serial, text, a in arts
    )
    v = result.volume_mm
    title = "Interim check" if result.interim else "Acceptance test"
    html = f"""<!doctype html><html><head><meta charset="utf-8">
<title>{escape(title)} {escape(result.cell)}</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #aaa;padding:.2em .6em;text-align:right}}td:first-child{{text-align:left}}
.pass{{color:#070}}.fail{{color:#b00}}</style></head><body>
<h1>{escape(title)} after {escape(result.kind)}: {escape(result.verdict.upper())}</h1>
<p>Cell <b>{escape(result.cell)}</b>; measuring volume {v["width"]:.0f} x {v["height"]:.0f} x {v["depth"]:.0f}
mm (L0 = {v["L0"]:.0f} mm); geometry: {escape(result.geometry_source)}.</p>
<p>{escape(note)}</p>
<h2>Figures (worst position, um) against the maximum permissible errors</h2>
<table><tr><th>figure</th><th>measured</th><th>MPE</th><th></th></tr>{rows}</table>
<h2>Every position (um)</h2>
<table><tr><th>position</th><th>PF (sphere 1 / 2)</th><th>PS (sphere 1 / 2)</th><th>SD</th><th>F</th>
<th>RMS residual</th><th>points</th><th>excluded (0.3 %)</th><th>error</th></tr>{pos_rows}</table>
<h2>Artefacts (calibration certificate)</h2>
<table><tr><th>artefact</th><th>serial</th><th>calibrated values</th><th>laboratory</th><th>date</th>
<th>U (k=2), um</th></tr>{art_rows}</table>
<p>PF: range of radial residuals of the least-squares sphere; PS: least-squares diameter minus calibrated
(both taken on the sphere's positions when the test has them, else on the ball bar's spheres);
SD: least-squares centre distance minus calibrated; F: range of residuals to the least-squares plane. The
0.3 % of points with the largest residuals are excluded before the final fit (the guideline's rule).</p>
</body></html>
"""
    write_atomic(path, html.encode())
