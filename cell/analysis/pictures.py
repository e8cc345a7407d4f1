"""Pictures of an error map for the HTML report: colour views of the points, a colour bar and a histogram.

Each view is an orthographic projection of the points drawn with a depth buffer (the nearest point wins each
pixel) and coloured by deviation, encoded as PNG with Pillow; the colour bar and the histogram are HTML and
SVG, so no plotting library is imported. Why not matplotlib's 3D scatter: it sorts and rasterises every marker
as a path and took 4 s of CPU for four views of 100k points (and 0.5 s to import), more than the whole error
map; this takes a few tens of milliseconds per view.

Units: mm; deviations + outside the material. Colours: the "jet" map clipped at ``limit_mm`` either side.
"""

from __future__ import annotations

import base64
import io
from typing import Any

import numpy as np
from numpy.typing import NDArray

# (name, elevation, azimuth) in degrees, matplotlib's convention: the eye at
# (cos e cos a, cos e sin a, sin e) looking at the centre.
VIEWS = (("top (-z)", 90, -90), ("front", 0, -90), ("side", 0, 0), ("iso", 30, -60))
JET_STOPS = ((0.0, "#00007f"), (0.125, "#0000ff"), (0.375, "#00ffff"), (0.625, "#ffff00"), (0.875, "#ff0000"))


def jet(x: NDArray) -> NDArray[np.uint8]:
    """RGB (N, 3) uint8 of values in [0, 1] on the jet map (blue, cyan, yellow, red)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)[:, None]
    rgb = np.clip(1.5 - np.abs(4.0 * x - np.array([3.0, 2.0, 1.0])), 0.0, 1.0)
    return (255 * rgb + 0.5).astype(np.uint8)


def view_axes(elev_deg: float, azim_deg: float) -> tuple[NDArray, NDArray, NDArray]:
    """Right, up and towards-the-eye unit vectors of a view, in the points' frame."""
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    return right, np.cross(eye, right), eye


def render_view(
    points_mm: NDArray, rgb: NDArray[np.uint8], elev_deg: float, azim_deg: float, size_px: int = 360
) -> NDArray[np.uint8]:
    """(size, size, 3) image of the points seen from (elev, azim), true proportions, white background."""
    right, up, eye = view_axes(elev_deg, azim_deg)
    u, v, depth = points_mm @ right, points_mm @ up, points_mm @ eye
    img = np.full((size_px, size_px, 3), 255, np.uint8)
    if len(u) == 0:
        return img
    span = max(float(np.ptp(u)), float(np.ptp(v)), 1e-9)
    scale = (size_px - 5) / span
    col = ((u - (u.min() + u.max()) / 2) * scale + size_px / 2).astype(np.int64).clip(0, size_px - 1)
    row = ((-(v - (v.min() + v.max()) / 2)) * scale + size_px / 2).astype(np.int64).clip(0, size_px - 1)
    pix = row * size_px + col
    order = np.lexsort((-depth, pix))  # by pixel, nearest first
    first = np.r_[True, pix[order][1:] != pix[order][:-1]]
    front = order[first]
    flat = img.reshape(-1, 3)
    flat[pix[front]] = rgb[front]
    # close the one-pixel gaps between sparse points: an empty pixel takes a filled neighbour's colour
    filled: NDArray[np.bool_] = np.zeros(size_px * size_px, bool)
    filled[pix[front]] = True
    filled = filled.reshape(size_px, size_px)
    for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        src_ok = np.roll(filled, (dr, dc), axis=(0, 1))
        take = ~filled & src_ok
        img[take] = np.roll(img, (dr, dc), axis=(0, 1))[take]
        filled |= take
    return img


def png_base64(img: NDArray[np.uint8]) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=1)  # speed over size
    return base64.b64encode(buf.getvalue()).decode("ascii")


def error_map_views(
    points_mm: NDArray,
    deviation_mm: NDArray,
    limit_mm: float,
    keep: NDArray[np.bool_],
    max_points: int = 100_000,
) -> list[dict[str, Any]]:
    """The four standard views as base64 PNG: ``{"name", "elev_deg", "azim_deg", "png"}`` each.

    Above ``max_points`` a random sample is drawn, but every point in ``keep`` (out of tolerance) stays."""
    if len(points_mm) > max_points:
        rest = np.flatnonzero(~keep)
        pick = np.random.default_rng(0).choice(rest, min(len(rest), max_points), replace=False)
        sel = np.sort(np.concatenate([pick, np.flatnonzero(keep)]))
        points_mm, deviation_mm = points_mm[sel], deviation_mm[sel]
    rgb = jet((np.asarray(deviation_mm) + limit_mm) / (2 * limit_mm))
    return [
        {"name": n, "elev_deg": e, "azim_deg": a, "png": png_base64(render_view(points_mm, rgb, e, a))}
        for n, e, a in VIEWS
    ]


def colour_bar_html(limit_mm: float) -> str:
    """The views' colour scale as a CSS gradient with its ends and centre labelled in mm."""
    stops = ", ".join(f"{c} {100 * x:.1f}%" for x, c in JET_STOPS) + ", #7f0000 100%"
    return (
        '<div style="width:360px"><div style="height:14px;background:linear-gradient(to right, '
        f'{stops})"></div><div style="display:flex;justify-content:space-between;font-size:small">'
        f"<span>{-limit_mm:+.3f}</span><span>0 mm</span><span>{limit_mm:+.3f}</span></div></div>"
    )


def histogram_svg(deviation_mm: NDArray, lower_mm: float, upper_mm: float, bins: int = 100) -> str:
    """SVG histogram of the deviations (mm) with the tolerance limits as red lines."""
    w, h, pad = 600, 220, 30
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if len(dev) == 0:
        return "<p>(no points)</p>"
    lo, hi = float(min(dev.min(), lower_mm)), float(max(dev.max(), upper_mm))
    if hi - lo < 1e-12:
        lo, hi = lo - 1e-3, hi + 1e-3
    counts, edges = np.histogram(dev, bins=bins, range=(lo, hi))
    sx = (w - 2 * pad) / (hi - lo)
    sy = (h - 2 * pad) / max(int(counts.max()), 1)
    bars = "".join(
        f'<rect x="{pad + (edges[i] - lo) * sx:.1f}" y="{h - pad - c * sy:.1f}" '
        f'width="{max((edges[i + 1] - edges[i]) * sx - 0.5, 0.5):.1f}" height="{c * sy:.1f}" fill="#666"/>'
        for i, c in enumerate(counts)
        if c
    )
    lines = "".join(
        f'<line x1="{pad + (t - lo) * sx:.1f}" x2="{pad + (t - lo) * sx:.1f}" y1="{pad / 2}" '
        f'y2="{h - pad}" stroke="red"/>'
        for t in (lower_mm, upper_mm)
    )
    axis = (
        f'<text x="{pad}" y="{h - 8}" font-size="11">{lo:+.3f}</text>'
        f'<text x="{w - pad}" y="{h - 8}" font-size="11" text-anchor="end">{hi:+.3f}</text>'
        f'<text x="{w / 2}" y="{h - 8}" font-size="11" text-anchor="middle">deviation (mm)</text>'
        f'<text x="4" y="{pad / 2 + 4}" font-size="11">max {int(counts.max())} points/bin</text>'
    )
    return f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}">{bars}{lines}{axis}</svg>'
