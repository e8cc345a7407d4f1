"""The report's interactive 3D deviation view: a plotly figure of a decimated cloud, embedded offline.

The figure holds at most ``max_points`` measured points, every out-of-tolerance one among them while they are
fewer than half of that, coordinates and deviations as float32 (plotly's base64 typed arrays); the nominal
surface that was not measured (grey), and the out-of-tolerance regions as numbered flags matching the report's
table. Colours come from :class:`cell.analysis.colour_scale.BandedScale` as a plotly colour scale with hard
steps at the limits. It is written as the dict plotly's ``graph_objects`` would make of it (with plotly's
default template) and encoded as plotly encodes it: importing and running ``graph_objects``' validators costs
0.2-0.4 s of CPU per report. tests/test_report_page.py has plotly validate the dict and checks that plotly's
own figure of it is the same JSON.

plotly.js comes from the plotly wheel (``plotly.offline.get_plotlyjs``, 4.8 MB) and is embedded in the
report gzip-compressed and base64-encoded (2.0 MB); the page inflates it with the browser's
``DecompressionStream`` (Chromium 80, Firefox 113, Safari 16.4 and later) and draws the figure. So the
report stays one file that opens without a network, at less than half the size of the plain script; a
browser without ``DecompressionStream`` says so where the view would be and the static views still show the
map.
"""

from __future__ import annotations

import base64
import gzip
import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.analysis.colour_scale import UNMEASURED, BandedScale, css_rgb
from cell.analysis.formatting import signed

MARKER_PX = 3.0  # screen pixels: enough for the decimated cloud to read as a surface
# a JavaScript condition that holds once the page's 3D view is drawn (or failed, or the page has none)
READY = "!document.getElementById('view3d') || document.getElementById('view3d').dataset.ready !== undefined"


@lru_cache(maxsize=1)
def plotly_js_gzip_base64() -> str:
    """plotly.js from the installed plotly wheel, gzip-compressed (deterministic: no time stamp), base64.

    Compressing 4.8 MB at level 9 costs 0.3 s of CPU, a sixth of a whole ``cell compare``: the result is kept
    in the user's cache folder (:func:`_cache_dir`), named by the script's SHA-256, and read from there while
    the script is the same; a cache that cannot be read or written is only slower."""
    from plotly.offline import get_plotlyjs

    script = get_plotlyjs().encode("utf-8")
    cached = _cache_dir() / f"plotly-{hashlib.sha256(script).hexdigest()[:20]}.js.gz.b64"
    try:
        return cached.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError):
        pass
    packed = base64.b64encode(gzip.compress(script, 9, mtime=0)).decode("ascii")
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        part = cached.with_name(f"{cached.name}.{os.getpid()}.part")
        part.write_text(packed, encoding="ascii")
        os.replace(part, cached)  # whole or absent, however many reports run at once
    except OSError:
        pass
    return packed


def _cache_dir() -> Path:
    """Where derived files are kept between runs: $CELL_CACHE_DIR, else $XDG_CACHE_HOME/inspection-cell,
    else ~/.cache/inspection-cell."""
    if os.environ.get("CELL_CACHE_DIR"):
        return Path(os.environ["CELL_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "inspection-cell"


def decimate(n_points: int, keep: NDArray[np.bool_], max_points: int, seed: int = 0) -> NDArray[np.int64]:
    """Indices (ascending) of at most ``max_points`` of ``n_points``: every ``keep`` point while they are
    at most half of ``max_points`` (else a random half of them), the rest a uniform random sample. The
    inspection's cloud is already merged on a voxel grid, so a random sample is an even one."""
    if n_points <= max_points:
        return np.arange(n_points)
    rng = np.random.default_rng(seed)
    kept = np.flatnonzero(keep)
    if len(kept) > max_points // 2:
        kept = rng.choice(kept, max_points // 2, replace=False)
    rest = np.flatnonzero(~keep)
    pick = rng.choice(rest, min(len(rest), max_points - len(kept)), replace=False)
    return np.sort(np.concatenate([kept, pick]))


def _typed(values: NDArray) -> dict[str, str]:
    """A float32 array as plotly's base64 typed array (little-endian bytes)."""
    data = np.ascontiguousarray(values, dtype="<f4").tobytes()
    return {"dtype": "f4", "bdata": base64.b64encode(data).decode("ascii")}


def _xyz(points: NDArray) -> dict[str, dict[str, str]]:
    p = np.asarray(points, np.float32)
    return {"x": _typed(p[:, 0]), "y": _typed(p[:, 1]), "z": _typed(p[:, 2])}


@lru_cache(maxsize=1)
def _template() -> dict[str, Any]:
    """plotly's default template ("plotly"), from the plotly wheel's JSON as graph_objects applies it."""
    from importlib.resources import files

    return dict(json.loads((files("plotly") / "package_data" / "templates" / "plotly.json").read_text()))


def figure(
    points_mm: NDArray,
    deviation_mm: NDArray,
    scale: BandedScale,
    keep: NDArray[np.bool_],
    *,
    unmeasured_mm: NDArray | None = None,
    labels: list[tuple[str, NDArray, str]] = (),  # type: ignore[assignment]
    max_points: int = 60_000,
) -> dict[str, Any]:
    """The plotly figure as a dict (``data``, ``layout``). ``labels``: (number, point, hover text)."""
    sel = decimate(len(points_mm), keep, max_points)
    c0, c1 = scale.range_mm
    ticks = sorted({c0, scale.lower_mm, scale.reference_mm, scale.upper_mm, c1})
    measured = dict(
        type="scatter3d",
        **_xyz(points_mm[sel]),
        mode="markers",
        name=f"measured ({len(sel):,} of {len(points_mm):,} points shown)".replace(",", "\u202f"),
        marker={
            "size": MARKER_PX,
            "color": _typed(deviation_mm[sel]),
            "colorscale": scale.plotly_colorscale(),
            "cmin": c0,
            "cmax": c1,
            "colorbar": {
                "title": {"text": "deviation (mm)"},
                "tickvals": ticks,
                "ticktext": [signed(t) for t in ticks],
                "len": 0.75,
                "thickness": 16,
            },
        },
        hovertemplate="x %{x:.2f}  y %{y:.2f}  z %{z:.2f} mm<br>deviation %{marker.color:+.3f} mm"
        "<extra></extra>",
    )
    data: list[Any] = [measured]
    if unmeasured_mm is not None and len(unmeasured_mm):
        data.append(
            dict(
                type="scatter3d",
                **_xyz(unmeasured_mm),
                mode="markers",
                name="not measured (nominal surface)",
                marker={"size": MARKER_PX, "color": css_rgb(UNMEASURED), "opacity": 0.55},
                hoverinfo="skip",
            )
        )
    callouts = []
    if labels:
        data.append(
            dict(
                type="scatter3d",
                **_xyz(np.array([p for _, p, _ in labels], np.float64)),
                mode="markers",
                name="out-of-tolerance regions",
                text=[t for t, _, _ in labels],
                marker={"size": 6, "symbol": "circle-open", "color": "#000", "line": {"width": 2}},
                hovertext=[h for _, _, h in labels],
                hoverinfo="text",
            )
        )
        # numbered flags drawn over the scene (never hidden behind points), their arrows at the worst point
        callouts = [
            {
                "x": float(p[0]),
                "y": float(p[1]),
                "z": float(p[2]),
                "text": f"<b>{t}</b>",
                "showarrow": True,
                "arrowhead": 0,
                "arrowwidth": 1.5,
                "ax": 26,
                "ay": -30,
                "bgcolor": "white",
                "bordercolor": "#111",
                "borderwidth": 1.5,
                "borderpad": 3,
                "font": {"size": 13, "color": "#000"},
            }
            for t, p, _ in labels
        ]
    axis = {"showbackground": False, "gridcolor": "#ddd", "zerolinecolor": "#bbb", "ticksuffix": ""}
    layout = dict(
        height=560,
        margin={"l": 0, "r": 0, "t": 0, "b": 0},
        paper_bgcolor="white",
        legend={"orientation": "h", "x": 0, "y": 1.0, "bgcolor": "rgba(255,255,255,0.7)"},
        scene={
            "aspectmode": "data",
            "xaxis": {**axis, "title": {"text": "x (mm)"}},
            "yaxis": {**axis, "title": {"text": "y (mm)"}},
            "zaxis": {**axis, "title": {"text": "z (mm)"}},
            "camera": {"eye": {"x": 1.25, "y": -1.9, "z": 1.25}},
            "annotations": callouts,
        },
        template=_template(),
    )
    return {"data": data, "layout": layout}


def figure_json(fig: dict[str, Any]) -> str:
    """The figure as JSON that is safe inside a ``<script type="application/json">`` element: compact, with
    ``<``, ``>`` and ``/`` escaped as plotly's ``to_json`` escapes them."""
    text = json.dumps(fig, separators=(",", ":"))
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("/", "\\u002f")


LOADER = """<script>
(async () => {
  const el = document.getElementById("view3d");
  if (location.hash === "#print") { el.dataset.ready = "skipped"; return; }
  try {
    const packed = document.getElementById("plotly-js-gz").textContent.trim();
    const bytes = Uint8Array.from(atob(packed), (c) => c.charCodeAt(0));
    const inflated = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    const script = document.createElement("script");
    script.textContent = await new Response(inflated).text();
    document.head.appendChild(script);
    const fig = JSON.parse(document.getElementById("fig3d").textContent);
    el.textContent = "";
    await Plotly.newPlot(el, fig.data, fig.layout, {displaylogo: false, responsive: true,
      toImageButtonOptions: {scale: 2, filename: "deviation-3d"}});
    el.dataset.ready = "1";
  } catch (err) {
    el.textContent = "The 3D view needs a current browser (" + err + "); the views below show the same map.";
    el.dataset.ready = "error";
  }
})();
</script>"""


def view3d_html(fig: dict[str, Any]) -> str:
    """The 3D view's element, its figure, plotly.js (compressed) and the loader that draws it."""
    return (
        '<div id="view3d" class="view3d">loading the 3D view&hellip;</div>'
        f'<script id="fig3d" type="application/json">{figure_json(fig)}</script>'
        f'<script id="plotly-js-gz" type="application/octet-stream">{plotly_js_gzip_base64()}</script>'
        f"{LOADER}"
    )
