"""Report pictures drawn without a plotting library: orientation, depth order and colour scale."""

from __future__ import annotations

import numpy as np

from cell.analysis.pictures import histogram_svg, jet, render_view


def test_jet_runs_from_dark_blue_through_green_to_dark_red() -> None:
    c = jet(np.array([0.0, 0.5, 1.0, -3.0, 7.0]))
    assert c[0].tolist() == [0, 0, 128] and c[2].tolist() == [128, 0, 0]
    assert c[1][1] == 255 and c[1][0] == c[1][2]  # green in the middle
    assert (c[3] == c[0]).all() and (c[4] == c[2]).all()  # clipped outside the scale


def test_top_view_puts_plus_x_right_and_plus_y_up() -> None:
    pts = np.array([[-10.0, -10, 0], [10, -10, 0], [-10, 10, 0], [10, 10, 0]])
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [0, 0, 0]], np.uint8)
    img = render_view(pts, rgb, 90, -90, size_px=64)
    red, green, blue = (np.argwhere((img == v).all(-1)) for v in rgb[:3])  # (row, col) of each colour
    assert len(red) and len(green) and len(blue)
    assert green[:, 1].min() > red[:, 1].max()  # +x to the right
    assert blue[:, 0].max() < red[:, 0].min()  # +y up


def test_the_nearest_point_wins_its_pixel() -> None:
    # two points on one line of sight of the front view (the eye at -y): the one at y = -5 is nearer
    pts = np.array([[0.0, -5.0, 0.0], [0.0, 5.0, 0.0], [3.0, 0.0, 3.0]])
    rgb = np.array([[255, 0, 0], [0, 0, 255], [0, 255, 0]], np.uint8)
    img = render_view(pts, rgb, 0, -90, size_px=32)
    assert (img == (255, 0, 0)).all(-1).any() and not (img == (0, 0, 255)).all(-1).any()
    img = render_view(pts, rgb, 0, 90, size_px=32)  # from the other side the blue one is nearer
    assert (img == (0, 0, 255)).all(-1).any() and not (img == (255, 0, 0)).all(-1).any()


def test_histogram_bars_sum_to_the_points() -> None:
    dev = np.r_[np.zeros(30), np.full(10, 0.5)]
    svg = histogram_svg(dev, -0.3, 0.3, bins=10)
    assert svg.count("<rect") == 2 and svg.count('stroke="red"') == 2
