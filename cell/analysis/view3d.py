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

The figure's point arrays (60 000 points: 1.28 MB as plotly's base64 float32) are embedded packed
(:func:`pack_arrays`): each as int32 steps (coordinates :data:`COORD_STEP_MM`, 1 um, a tenth of what the
hover shows; deviations :data:`DEVIATION_STEP_MM`, 0.1 um, the views' storage step), byte-planes split so
that deflate finds the slowly changing high bytes, gzip-compressed and base64-encoded, 0.5 MB; the loader
inflates them as it does plotly.js and hands plotly the float32 arrays. The numbers of the run stay in
``cloud.ply`` and ``report.json``; the view is a picture of them.
"""

from __future__ import annotations

import base64
import gzip
import hashlib
import json
import os
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.analysis.colour_scale import UNMEASURED, BandedScale, css_rgb
from cell.analysis.formatting import signed
from cell.user_cache import cache_dir

COORD_STEP_MM = 1e-3  # the packed 3D view's coordinate step (the hover shows 0.01 mm)
DEVIATION_STEP_MM = 1e-4  # and its deviation step (the hover shows 0.001 mm)
MARKER_PX = 3.0  # screen pixels: enough for the decimated cloud to read as a surface
# a JavaScript condition that holds once the page's 3D view is drawn (or failed, or the page has none)
READY = "!document.getElementById('view3d') || document.getElementById('view3d').dataset.ready !== undefined"


@lru_cache(maxsize=1)
def plotly_js_gzip_base64() -> str:
    """plotly.js from the installed plotly wheel, gzip-compressed (deterministic: no time stamp), base64.

    Compressing 4.8 MB at level 9 costs 0.3 s of CPU, a sixth of a whole ``cell compare``: the result is kept
    in the user's cache folder (:func:`cell.user_cache.cache_dir`), named by the script's SHA-256, and read
    from there while the script is the same; a cache that cannot be read or written is only slower."""
    from plotly.offline import get_plotlyjs

    script = get_plotlyjs().encode("utf-8")
    cached = cache_dir() / f"plotly-{hashlib.sha256(script).hexdigest()[:20]}.js.gz.b64"
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


def pack_arrays(fig: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The figure with its traces' float32 point arrays (``x``, ``y``, ``z``, ``marker.color``) replaced by
    ``{"packed": offset, "n": count, "step": mm}``, and those arrays as one gzip-compressed, base64-encoded
    blob: each array its values in int32 steps of ``step`` (``round(v / step)``), written as four byte
    planes (all lowest bytes, then the next, ...; little-endian), one array after another from ``offset``
    bytes. The loader (:data:`LOADER`) turns them back into float32 arrays of ``step * k``."""
    planes: list[bytes] = []
    offset = 0

    def packed(array: Any, step: float) -> Any:
        nonlocal offset
        if not (isinstance(array, dict) and array.get("dtype") == "f4"):
            return array
        values = np.frombuffer(base64.b64decode(array["bdata"]), dtype="<f4").astype(np.float64)
        steps = np.round(values / step)
        if len(steps) and not np.abs(steps).max() < 2**31:
            raise ValueError(f"3D view values beyond {2**31 * step:.0f} mm cannot be packed")
        data = steps.astype("<i4").view(np.uint8).reshape(-1, 4).T.tobytes()
        placeholder = {"packed": offset, "n": int(len(steps)), "step": step}
        planes.append(data)
        offset += len(data)
        return placeholder

    traces = []
    for trace in fig["data"]:
        trace = dict(trace)
        for axis in ("x", "y", "z"):
            if axis in trace:
                trace[axis] = packed(trace[axis], COORD_STEP_MM)
        if isinstance(trace.get("marker"), dict) and "color" in trace["marker"]:
            trace["marker"] = {
                **trace["marker"],
                "color": packed(trace["marker"]["color"], DEVIATION_STEP_MM),
            }
        traces.append(trace)
    # level 6: level 9 took 1.4 s of CPU on the 200k-point compare's 0.96 MB of planes for 1.3 % fewer bytes
    blob = base64.b64encode(gzip.compress(b"".join(planes), 6, mtime=0)).decode("ascii")
    return {**fig, "data": traces}, blob


def unpack_arrays(fig: dict[str, Any], blob: str) -> dict[str, Any]:
    """:func:`pack_arrays` undone in Python (the page does it in JavaScript): the figure with float32
    arrays (numpy) where the placeholders were."""
    raw = np.frombuffer(gzip.decompress(base64.b64decode(blob)), dtype=np.uint8)

    def unpacked(value: Any) -> Any:
        if not (isinstance(value, dict) and "packed" in value):
            return value
        n, at = int(value["n"]), int(value["packed"])
        steps = raw[at : at + 4 * n].reshape(4, n).T.copy().view("<i4").ravel()
        return (steps * value["step"]).astype(np.float32)

    traces = []
    for trace in fig["data"]:
        trace = {k: unpacked(v) for k, v in trace.items()}
        if isinstance(trace.get("marker"), dict):
            trace["marker"] = {k: unpacked(v) for k, v in trace["marker"].items()}
        traces.append(trace)
    return {**fig, "data": traces}


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
    const arrays = document.getElementById("fig3d-arrays").textContent.trim();
    const zipped = Uint8Array.from(atob(arrays), (c) => c.charCodeAt(0));
    const raw = new Uint8Array(await new Response(
      new Blob([zipped]).stream().pipeThrough(new DecompressionStream("gzip"))).arrayBuffer());
    const unpack = (v) => {  // int32 steps in four byte planes -> float32 (view3d.pack_arrays)
      if (v === null || typeof v !== "object" || v.packed === undefined) return v;
      const n = v.n, bytes = new Uint8Array(4 * n);
      for (let b = 0; b < 4; b++) {
        const plane = raw.subarray(v.packed + b * n, v.packed + (b + 1) * n);
        for (let i = 0; i < n; i++) bytes[4 * i + b] = plane[i];
      }
      const steps = new DataView(bytes.buffer), out = new Float32Array(n);
      for (let i = 0; i < n; i++) out[i] = steps.getInt32(4 * i, true) * v.step;
      return out;
    };
    for (const trace of fig.data) {
      for (const axis of ["x", "y", "z"]) if (axis in trace) trace[axis] = unpack(trace[axis]);
      if (trace.marker) trace.marker.color = unpack(trace.marker.color);
    }
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
    """The 3D view's element, its figure (its point arrays packed: :func:`pack_arrays`), plotly.js
    (compressed) and the loader that draws it."""
    layout, arrays = pack_arrays(fig)
    return (
        '<div id="view3d" class="view3d">loading the 3D view&hellip;</div>'
        f'<script id="fig3d" type="application/json">{figure_json(layout)}</script>'
        f'<script id="fig3d-arrays" type="application/octet-stream">{arrays}</script>'
        f'<script id="plotly-js-gz" type="application/octet-stream">{plotly_js_gzip_base64()}</script>'
        f"{LOADER}"
    )
