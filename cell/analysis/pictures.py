"""Static pictures of an error map for the report (and its printout): four shaded views with the defects
labelled and the unmeasured surface hatched, and a histogram.

Each view is an orthographic projection of the points drawn with a depth buffer (the nearest point wins each
pixel), coloured by :class:`cell.analysis.colour_scale.BandedScale`, shaded by the normal of the depth image
(light from the upper left, so the part reads as a solid) and encoded as PNG with Pillow. The nominal
surface samples that no point covered (``Coverage.covered`` false) are drawn as hatching behind the measured
points. Out-of-tolerance regions are labelled with their number at their extreme point where that point is
visible. Why not matplotlib's 3D scatter: it rasterises every marker as a path, seconds for 100k points;
this takes tens of milliseconds per view. The image filters are OpenCV's (scipy.ndimage costs 0.4 s of CPU
to import, a third of a whole ``cell compare``).

Units: mm, deviations + outside the material; views in matplotlib's convention (elevation, azimuth: the eye
at (cos e cos a, cos e sin a, sin e) looking at the centre).
"""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.analysis.colour_scale import UNMEASURED, BandedScale
from cell.analysis.formatting import count, signed

VIEWS = (("top", 90, -90), ("front", 0, -90), ("right", 0, 0), ("iso", 30, -60))
LIGHT = np.array([-0.45, 0.55, 1.0]) / np.linalg.norm([-0.45, 0.55, 1.0])  # right, up, towards the eye


def _dot(v: NDArray, axis: NDArray) -> NDArray:
    """``v @ axis`` over the last dimension (3) written out: OpenBLAS's threads make a (N, 3) @ (3,) product
    5-15x dearer in CPU than these three products on a shared machine (0.35 s of the four views' 1.1 s)."""
    return v[..., 0] * axis[0] + v[..., 1] * axis[1] + v[..., 2] * axis[2]


def view_axes(elev_deg: float, azim_deg: float) -> tuple[NDArray, NDArray, NDArray]:
    """Right, up and towards-the-eye unit vectors of a view, in the points' frame."""
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    return right, np.cross(eye, right), eye


@dataclass(frozen=True)
class ViewFrame:
    """Where points land in one view's image: columns right, rows down, depth towards the eye (mm)."""

    axes: tuple[NDArray, NDArray, NDArray]
    centre_uv: NDArray
    scale_px_per_mm: float
    width_px: int
    height_px: int
    strip_px: int = 0  # below the points: room for the axis triad

    @classmethod
    def fit(
        cls,
        points_mm: NDArray,
        elev_deg: float,
        azim_deg: float,
        width_px: int,
        min_height_px: int = 200,
        margin_px: int = 24,
        strip_px: int = 36,
    ) -> ViewFrame:
        """The frame that shows every point, true proportions, centred, ``width_px`` wide and as high as the
        points need (``min_height_px`` .. ``width_px``) plus a ``strip_px`` strip below them."""
        axes = view_axes(elev_deg, azim_deg)
        uv = np.column_stack([_dot(points_mm, axes[0]), _dot(points_mm, axes[1])])
        lo, hi = uv.min(0), uv.max(0)
        span_u, span_v = max(float(hi[0] - lo[0]), 1e-9), max(float(hi[1] - lo[1]), 1e-9)
        inner = width_px - 2 * margin_px
        scale = min(inner / span_u, inner / span_v)
        height = int(np.clip(np.ceil(span_v * scale) + 2 * margin_px, min_height_px, width_px))
        return cls(axes, (lo + hi) / 2, scale, width_px, height + strip_px, strip_px)

    def project(self, points_mm: NDArray) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray]:
        """Column, row (pixels) and depth (mm, larger is nearer) of each point."""
        right, up, eye = self.axes
        u = (_dot(points_mm, right) - self.centre_uv[0]) * self.scale_px_per_mm + self.width_px / 2
        v = (
            -(_dot(points_mm, up) - self.centre_uv[1]) * self.scale_px_per_mm
            + (self.height_px - self.strip_px) / 2
        )
        col = np.clip(np.floor(u), 0, self.width_px - 1).astype(np.int64)
        row = np.clip(np.floor(v), 0, self.height_px - 1).astype(np.int64)
        return col, row, _dot(points_mm, eye)


def _splat(
    col: NDArray, row: NDArray, depth: NDArray, k: int, shape: tuple[int, int]
) -> tuple[NDArray, NDArray, NDArray]:
    """Each pixel widened to a k x k square (clipped to the image of ``shape`` (rows, columns)); flat pixel
    index, depth and index of the source point of each drawn pixel."""
    h, w = shape
    if k <= 1:
        return row * w + col, depth, np.arange(len(col))
    off = np.arange(k) - k // 2
    dr, dc = (g.ravel() for g in np.meshgrid(off, off, indexing="ij"))
    r = np.clip(row[:, None] + dr[None, :], 0, h - 1).ravel()
    c = np.clip(col[:, None] + dc[None, :], 0, w - 1).ravel()
    src = np.repeat(np.arange(len(col)), len(dr))
    return r * w + c, depth[src], src


def _gaussian(img: NDArray, sigma: float) -> NDArray:
    """Gaussian smoothing, mirrored at the border (scipy.ndimage.gaussian_filter's, truncated at 4 sigma),
    by OpenCV: scipy.ndimage costs 0.4 s of CPU to import."""
    import cv2

    k = 2 * int(4.0 * sigma + 0.5) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, borderType=cv2.BORDER_REFLECT)


def _shade(depth_img: NDArray, scale_px_per_mm: float) -> NDArray:
    """Lambert shading (0.5 .. 1) of a depth image (mm, NaN where empty) from its normals, the depth first
    smoothed over a few pixels (NaN-aware) so that measurement noise does not speckle the picture."""
    ok = np.isfinite(depth_img)
    weight = _gaussian(ok.astype(np.float64), 1.2)
    smooth = _gaussian(np.where(ok, depth_img, 0.0), 1.2) / np.maximum(weight, 1e-9)
    g_row, g_col = np.gradient(np.where(ok, smooth, np.nan))
    # the unit normal (-g_col s, g_row s, 1) / norm . LIGHT, plane by plane (no (H, W, 3) stack: a third of
    # the time, the same bits)
    nx, ny = -g_col * scale_px_per_mm, g_row * scale_px_per_mm
    norm = np.sqrt(nx * nx + ny * ny + 1.0)
    lam = np.clip(nx / norm * LIGHT[0] + ny / norm * LIGHT[1] + 1.0 / norm * LIGHT[2], 0.0, 1.0)
    return np.where(np.isfinite(lam), 0.5 + 0.5 * lam, 1.0)


def _zbuffer(pix: NDArray, depth: NDArray, n_pixels: int) -> tuple[NDArray[np.int64], NDArray]:
    """Per pixel (flat) the index of the nearest entry drawn there (-1: none; of equally near ones the first)
    and its depth (NaN: none); ``depth`` finite. A compiled loop (:mod:`cell.analysis._picture_kernels`)."""
    from cell.analysis import kernels

    return kernels.get("zbuffer")(
        np.ascontiguousarray(pix, np.int64), np.ascontiguousarray(depth, np.float64), int(n_pixels)
    )


def render_view(
    frame: ViewFrame,
    points_mm: NDArray,
    rgb: NDArray[np.uint8],
    unmeasured_mm: NDArray | None = None,
    unmeasured_px: int = 1,
    point_px: int = 1,
) -> tuple[NDArray[np.uint8], NDArray]:
    """The shaded image (height, width, 3) of the coloured points as a surface, and the hatched unmeasured
    samples where no measured surface lies in front of them; and the depth image (mm, NaN where empty).

    ``point_px``: the points' spacing in pixels: each point is drawn that size and the holes between points
    up to three times that are filled from the nearest point, so that a sparse cloud hides what lies behind
    it.
    ``unmeasured_px``: the unmeasured samples' spacing in pixels (each drawn as a square that size)."""
    shape = (frame.height_px, frame.width_px)
    col, row, depth = frame.project(points_mm)
    pix, dep, src = _splat(col, row, depth, max(1, point_px // 2 + 1), shape)
    winner, depth_img = _zbuffer(pix, dep, shape[0] * shape[1])
    flat = np.full((shape[0] * shape[1], 3), 255, np.uint8)
    hit = winner >= 0
    flat[hit] = rgb[src[winner[hit]]]
    img, depth_img = flat.reshape(*shape, 3), depth_img.reshape(shape)
    _drop_seen_through(depth_img, 4 * point_px + 1, max(1.0, 4 * point_px / frame.scale_px_per_mm))
    _fill_holes(img, depth_img, 3 * point_px)
    img[~np.isfinite(depth_img)] = 255
    if unmeasured_mm is not None and len(unmeasured_mm):
        uc, ur, ud = frame.project(unmeasured_mm)
        upix, udep, _ = _splat(uc, ur, ud, unmeasured_px, shape)
        _, u_depth = _zbuffer(upix, udep, shape[0] * shape[1])
        u_depth = u_depth.reshape(shape)
        behind = max(2.0, unmeasured_px / frame.scale_px_per_mm)  # mm: samples on the nominal, points near it
        show = np.isfinite(u_depth) & ~(np.isfinite(depth_img) & (depth_img > u_depth - behind))
        rr, cc = np.nonzero(show)
        stripe = ((rr + cc) // 3) % 2 == 0
        img[rr, cc] = np.where(stripe[:, None], np.asarray(UNMEASURED, np.uint8), np.uint8(236))
        depth_img[show] = np.nan
    lit = np.isfinite(depth_img)
    shade = _shade(depth_img, frame.scale_px_per_mm)
    img[lit] = (img[lit] * shade[lit][:, None]).astype(np.uint8)
    return img, depth_img


def _drop_seen_through(depth_img: NDArray, window_px: int, thickness_mm: float) -> None:
    """Empty the pixels that show a point far behind the surface around them: seen through a hole between
    the nearer surface's points, they belong to a face the nearer one hides (a sparse cloud's back side)."""
    import cv2

    # the nearest depth within the window (scipy.ndimage.maximum_filter's answer: its mirrored border only
    # repeats pixels inside the window)
    nearest = cv2.dilate(
        np.where(np.isfinite(depth_img), depth_img, -np.inf), np.ones((window_px, window_px), np.uint8)
    )
    depth_img[depth_img < nearest - thickness_mm] = np.nan


def _fill_holes(img: NDArray[np.uint8], depth_img: NDArray, max_px: int) -> None:
    """Empty pixels within ``max_px`` of a drawn one take the nearest drawn pixel's colour and depth.
    OpenCV's distance transform with the nearest drawn pixel's label (its 5x5 mask: distances within 2 %
    of the Euclidean one) instead of scipy.ndimage's exact one, which costs 0.4 s of CPU to import."""
    import cv2

    empty = ~np.isfinite(depth_img)
    if empty.all() or not empty.any():
        return
    dist, label = cv2.distanceTransformWithLabels(
        empty.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    drawn = np.flatnonzero(~empty)
    source = np.zeros(int(label.max()) + 1, np.int64)
    source[label.ravel()[drawn]] = drawn  # each drawn pixel carries a label of its own
    fill = np.flatnonzero(empty & (dist <= max_px))
    src = source[label.ravel()[fill]]
    img.reshape(-1, img.shape[-1])[fill] = img.reshape(-1, img.shape[-1])[src]
    depth_img.reshape(-1)[fill] = depth_img.reshape(-1)[src]


def _font(size: int) -> Any:
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def draw_labels(
    img: NDArray[np.uint8], frame: ViewFrame, depth_img: NDArray, labels: list[tuple[str, NDArray]]
) -> NDArray[np.uint8]:
    """Numbered flags with leader lines at the labelled points that this view shows (a point hidden behind
    the surface nearer the eye is not labelled here)."""
    from PIL import Image, ImageDraw

    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    font = _font(13)
    tol_mm = 3.0 / frame.scale_px_per_mm + 1.0  # a surface seen obliquely changes depth across pixels
    shape = (frame.height_px, frame.width_px)
    taken: list[tuple[int, int]] = []
    for text, xyz in labels:
        cols, rows, depths = frame.project(np.asarray(xyz, np.float64)[None, :])
        c, r, d = int(cols[0]), int(rows[0]), float(depths[0])
        near = depth_img[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2]
        if not np.isfinite(near).any() or d < np.nanmedian(near) - tol_mm:
            continue  # hidden in this view
        lx, ly = _free_spot(c, r, taken, shape)
        taken.append((lx, ly))
        draw.line([(c, r), (lx, ly)], fill=(20, 20, 20), width=2)
        draw.ellipse([c - 4, r - 4, c + 4, r + 4], outline=(20, 20, 20), width=2)
        w = max(22, int(draw.textlength(text, font=font)) + 10)
        draw.rounded_rectangle(
            [lx - w // 2, ly - 11, lx + w // 2, ly + 11], 6, fill="white", outline=(20, 20, 20), width=2
        )
        draw.text((lx, ly), text, fill=(0, 0, 0), font=font, anchor="mm")
    return np.asarray(pil)


def _free_spot(c: int, r: int, taken: list[tuple[int, int]], shape: tuple[int, int]) -> tuple[int, int]:
    """Where a flag for the point (c, r) goes: the first of a ring of spots around it, farther out each
    round, that keeps clear of the flags already placed and inside the image."""
    h, w = shape
    for dist in (28, 46, 64, 82):
        for ang in (-45, -135, 45, 135, -90, 0, 180, 90):
            x = int(np.clip(c + dist * np.cos(np.radians(ang)), 16, w - 16))
            y = int(np.clip(r + dist * np.sin(np.radians(ang)), 14, h - 14))
            if all(abs(x - tx) > 30 or abs(y - ty) > 24 for tx, ty in taken):
                return x, y
    return int(np.clip(c + 28, 16, w - 16)), int(np.clip(r - 28, 14, h - 14))


def draw_triad(img: NDArray[np.uint8], frame: ViewFrame) -> NDArray[np.uint8]:
    """The part frame's x, y, z axes in the lower left corner, as they point in this view."""
    from PIL import Image, ImageDraw

    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    font = _font(11)
    right, up, _ = frame.axes
    o = np.array([26.0, frame.height_px - 12.0])
    for axis, name, colour in ((0, "x", (200, 30, 30)), (1, "y", (30, 140, 30)), (2, "z", (30, 60, 200))):
        e = np.eye(3)[axis]
        d = np.array([e @ right, -(e @ up)]) * 18
        if np.hypot(*d) < 3:  # along the line of sight
            draw.ellipse([o[0] - 3, o[1] - 3, o[0] + 3, o[1] + 3], outline=colour, width=2)
            draw.text((o[0] + 6, o[1] + 6), name, fill=colour, font=font, anchor="mm")
            continue
        draw.line([tuple(o), tuple(o + d)], fill=colour, width=2)
        draw.text(tuple(o + d * 1.45), name, fill=colour, font=font, anchor="mm")
    return np.asarray(pil)


def png_base64(img: NDArray[np.uint8]) -> str:
    """The image as base64 PNG. zlib level 1: a third of level 6's time (0.1 s instead of 0.3 s for the four
    views of a 200k-point cloud) for about a tenth more bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=False, compress_level=1)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def error_map_views(
    points_mm: NDArray,
    deviation_mm: NDArray,
    scale: BandedScale | None,
    keep: NDArray[np.bool_],
    *,
    unmeasured_mm: NDArray | None = None,
    unmeasured_spacing_mm: float | None = None,
    labels: list[tuple[str, NDArray]] = (),  # type: ignore[assignment]
    max_points: int = 150_000,
    width_px: int = 520,
    colours: NDArray[np.uint8] | None = None,
) -> list[dict[str, Any]]:
    """The four standard views as base64 PNG: ``{"name", "elev_deg", "azim_deg", "png"}`` each.

    Above ``max_points`` a random sample is drawn, but every point in ``keep`` (out of tolerance) stays.
    ``unmeasured_mm``: nominal surface samples no point covered, about ``unmeasured_spacing_mm`` apart;
    ``labels``: (text, point) flags; ``colours``: (N, 3) the points' colours when not the deviations' on
    ``scale`` (the uncertainty map)."""
    if len(points_mm) > max_points:
        rest = np.flatnonzero(~keep)
        pick = np.random.default_rng(0).choice(rest, min(len(rest), max_points), replace=False)
        sel = np.sort(np.concatenate([pick, np.flatnonzero(keep)]))
        points_mm, deviation_mm = points_mm[sel], deviation_mm[sel]
        colours = None if colours is None else colours[sel]
    if colours is None:
        if scale is None:
            raise ValueError("error_map_views needs a colour scale or the points' colours")
        colours = scale.rgb(deviation_mm)
    rgb = colours
    unmeasured = unmeasured_mm if unmeasured_mm is not None and len(unmeasured_mm) else None
    everything = points_mm if unmeasured is None else np.vstack([points_mm, unmeasured])
    spacing = point_spacing_mm(points_mm)
    out = []
    for name, e, a in VIEWS:
        frame = ViewFrame.fit(everything, e, a, width_px)
        k = 1
        if unmeasured is not None and unmeasured_spacing_mm:
            k = _px(unmeasured_spacing_mm * 1.2, frame)
        img, depth = render_view(frame, points_mm, rgb, unmeasured, k, _px(spacing, frame))
        img = draw_triad(draw_labels(img, frame, depth, list(labels)), frame)
        out.append({"name": name, "elev_deg": e, "azim_deg": a, "png": png_base64(img)})
    return out


def point_spacing_mm(points_mm: NDArray, sample: int = 4000) -> float:
    """Median distance from a point to its nearest other point (mm), from a random sample of points."""
    if len(points_mm) < 2:
        return 0.0
    from cell.analysis._point_grid import nearest_other, point_grid

    pick = np.random.default_rng(0).choice(len(points_mm), min(sample, len(points_mm)), replace=False)
    n_same, d = nearest_other(point_grid(points_mm), pick)
    d = np.where(n_same == 1, d, 0.0)  # a copy of the point is its nearest other one (left out below)
    return float(np.median(d[d > 0])) if (d > 0).any() else 0.0


def _px(length_mm: float, frame: ViewFrame) -> int:
    """A length as a whole number of pixels (1 .. 15) in the view."""
    return int(np.clip(np.ceil(length_mm * frame.scale_px_per_mm), 1, 15))


def histogram_svg(deviation_mm: NDArray, scale: BandedScale, bins: int = 90) -> str:
    """SVG histogram of the deviations (mm), bars in the scale's colours, the limits marked, and the count
    of points beyond each limit written beside it (a few hundred points of a dent do not show as bars
    beside millions)."""
    w, h, pad, top = 640, 210, 34, 26
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if len(dev) == 0:
        return "<p>(no points)</p>"
    margin = 0.3 * scale.span_mm
    lo = float(min(dev.min(), scale.lower_mm - margin))
    hi = float(max(dev.max(), scale.upper_mm + margin))
    counts, edges = np.histogram(dev, bins=bins, range=(lo, hi))
    sx = (w - 2 * pad) / (hi - lo)
    sy = (h - pad - top) / max(int(counts.max()), 1)
    colours = scale.rgb((edges[:-1] + edges[1:]) / 2)
    bars = "".join(
        f'<rect x="{pad + (edges[i] - lo) * sx:.1f}" y="{h - pad - c * sy:.1f}" '
        f'width="{max((edges[i + 1] - edges[i]) * sx - 0.6, 0.6):.1f}" height="{max(c * sy, 0.8):.1f}" '
        f'fill="rgb({colours[i][0]},{colours[i][1]},{colours[i][2]})" stroke="#777" stroke-width="0.3"/>'
        for i, c in enumerate(counts)
        if c
    )
    below, above = int((dev < scale.lower_mm).sum()), int((dev > scale.upper_mm).sum())
    marks = ""
    for t, n, anchor, dx in ((scale.lower_mm, below, "end", -4), (scale.upper_mm, above, "start", 4)):
        x = pad + (t - lo) * sx
        marks += (
            f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top - 8}" y2="{h - pad}" stroke="#111" '
            f'stroke-dasharray="4 3"/><text x="{x + dx:.1f}" y="{top - 12}" text-anchor="{anchor}">'
            f"{signed(t)} ({count(n)} beyond)</text>"
        )
    ticks = "".join(
        f'<line x1="{pad + (v - lo) * sx:.1f}" x2="{pad + (v - lo) * sx:.1f}" y1="{h - pad}" '
        f'y2="{h - pad + 4}" stroke="#333"/><text x="{pad + (v - lo) * sx:.1f}" y="{h - pad + 16}" '
        f'text-anchor="middle">{signed(v, 2)}</text>'
        for v in _nice_ticks(lo, hi)
    )
    axis = (
        f'<line x1="{pad}" x2="{w - pad}" y1="{h - pad}" y2="{h - pad}" stroke="#333"/>'
        f'<text x="{w / 2}" y="{h - 2}" text-anchor="middle">deviation (mm); bar heights: points per '
        f"bin, largest {count(int(counts.max()))}</text>"
    )
    return (
        f'<svg class="hist" xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {w} {h}" width="{w}" '
        f'height="{h}" font-size="11" font-family="sans-serif">{bars}{marks}{ticks}{axis}</svg>'
    )


def _nice_ticks(lo: float, hi: float, n: int = 8) -> list[float]:
    """Round tick values (1, 2 or 5 times a power of ten apart) inside [lo, hi]."""
    raw = (hi - lo) / n
    mag = 10 ** np.floor(np.log10(raw))
    step = mag * min((m for m in (1, 2, 5, 10) if m * mag >= raw), default=10)
    first = np.ceil(lo / step) * step
    return [round(float(v), 10) for v in np.arange(first, hi + 1e-12, step)]
