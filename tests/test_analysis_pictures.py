"""Report pictures drawn without a plotting library: orientation, depth order, the unmeasured surface, the
defect flags and the histogram."""

from __future__ import annotations

import numpy as np

from cell.analysis.colour_scale import BandedScale
from cell.analysis.pictures import ViewFrame, draw_labels, histogram_svg, render_view


def dominant(img: np.ndarray, channel: int) -> np.ndarray:
    """(row, col) of the pixels where ``channel`` clearly dominates (shading scales colours, not hues)."""
    c = img.astype(int)
    others = [k for k in range(3) if k != channel]
    return np.argwhere((c[..., channel] > 100) & (c[..., channel] > 2 * c[..., others].max(-1) + 20))


def grid(x0: float, x1: float, y0: float, y1: float, z: float = 0.0, step: float = 0.25) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step)), -1).reshape(-1, 2)
    return np.c_[g, np.full(len(g), z)]


def test_top_view_puts_plus_x_right_and_plus_y_up() -> None:
    quads = [grid(-10, -5, -10, -5), grid(5, 10, -10, -5), grid(-10, -5, 5, 10)]  # red, green, blue
    pts = np.vstack(quads)
    rgb = np.repeat(np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8), [len(q) for q in quads], 0)
    frame = ViewFrame.fit(pts, 90, -90, 128, strip_px=0)
    img, _ = render_view(frame, pts, rgb)
    red, green, blue = (dominant(img, k) for k in range(3))
    assert len(red) and len(green) and len(blue)
    assert green[:, 1].min() > red[:, 1].max()  # +x to the right
    assert blue[:, 0].max() < red[:, 0].min()  # +y up


def test_the_nearest_surface_wins_its_pixels() -> None:
    # two squares on one line of sight of the front view (the eye at -y): the one at y = -5 is nearer
    near, far = grid(-5, 5, -5, 5, z=0.0), grid(-5, 5, -5, 5, z=0.0)
    near = near[:, [0, 2, 1]] + [0, -5, 0]  # in the plane y = -5
    far = far[:, [0, 2, 1]] + [0, 5, 0]  # y = +5
    pts = np.vstack([near, far])
    rgb = np.repeat(np.array([[255, 0, 0], [0, 0, 255]], np.uint8), [len(near), len(far)], 0)
    for azim, seen, hidden in ((-90, 0, 2), (90, 2, 0)):
        frame = ViewFrame.fit(pts, 0, azim, 96, strip_px=0)
        img, _ = render_view(frame, pts, rgb)
        assert len(dominant(img, seen)) > 1000 and len(dominant(img, hidden)) == 0


def test_unmeasured_surface_is_hatched_where_nothing_measured_lies_in_front() -> None:
    """A plate measured on its left half, its nominal samples everywhere: the hatching shows on the right
    half only, and not at all when the samples lie behind a measured surface."""
    measured = grid(-10, 0, -10, 10)
    samples = grid(-10, 10, -10, 10, step=1.0)
    rgb = np.full((len(measured), 3), 200, np.uint8)
    frame = ViewFrame.fit(samples, 90, -90, 128, strip_px=0)
    img, depth = render_view(frame, measured, rgb, samples, unmeasured_px=5, point_px=1)
    dark = np.argwhere((img == 105).all(-1))  # the hatching's dark stripes (UNMEASURED)
    cols_left = np.flatnonzero(np.isfinite(depth).any(0))
    assert len(dark) > 200 and dark[:, 1].min() > cols_left.max() - 2
    behind = samples[samples[:, 0] < -1] - [0, 0, 20]  # 20 mm below the measured half
    img, _ = render_view(frame, measured, rgb, behind, unmeasured_px=5, point_px=1)
    assert not (img == 105).all(-1).any()


def test_defect_flags_are_drawn_where_the_defect_is_visible_only() -> None:
    plate = grid(-10, 10, -10, 10)
    rgb = np.full((len(plate), 3), 220, np.uint8)
    frame = ViewFrame.fit(plate, 90, -90, 160, strip_px=0)
    img, depth = render_view(frame, plate, rgb)
    on_top = draw_labels(img, frame, depth, [("1", np.array([0.0, 0.0, 0.0]))])
    assert (on_top != img).any(-1).sum() > 100  # the flag, its leader line and the number
    underneath = draw_labels(img, frame, depth, [("2", np.array([0.0, 0.0, -15.0]))])  # hidden by the plate
    assert (underneath == img).all()


def test_histogram_bars_and_the_points_beyond_each_limit() -> None:
    dev = np.r_[np.zeros(30), np.full(10, 0.5), np.full(3, -0.45)]
    svg = histogram_svg(dev, BandedScale(-0.3, 0.3), bins=20)
    assert svg.count("<rect") == 3 and svg.count('stroke-dasharray="4 3"') == 2  # 3 bins, 2 limits
    assert "(3 beyond)" in svg and "(10 beyond)" in svg
