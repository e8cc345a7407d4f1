"""The report page's stylesheet (cell.analysis.report_html): screen layout, and the print layout on A4 that
keeps the report to at most three pages (verdict, identity, key figures and the maps; the callouts and
statistics; alignment, calibration and measurement)."""

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
  flex: none; gap: 10px;
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
.uviews { grid-template-columns: repeat(4, 1fr); }
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
  .uviews { grid-template-columns: repeat(4, 40mm); }
  .unc-sec { break-inside: avoid; }
  .legend { width: 120mm !important; margin: 5px auto 0; font-size: 9px; }
  table { font-size: 9.5px; } th { font-size: 8.5px; } th, td { padding: 1.5px 6px; }
  .callouts-sec { break-before: page; }
  .stats-sec, table { break-inside: avoid; }
  h2, h3 { break-after: avoid; }
  .hist { width: 112mm; height: auto; }
  * { -webkit-print-color-adjust: exact; print-color-adjust: exact; }
}
"""
