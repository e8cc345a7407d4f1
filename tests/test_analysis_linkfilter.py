"""Link-clustering filter: injected outliers removed, true surface kept (>= 99.9 %)."""

from __future__ import annotations

import numpy as np
import pytest

from cell.analysis.linkfilter import depth_edges, link_cluster
from cell.errors import ConfigError


def _surface(h: int = 240, w: int = 320) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:h, 0:w] * 0.1  # 0.1 mm pixel pitch
    z = 50 + 0.2 * x + 0.5 * np.sin(x / 3) * np.cos(y / 4) + rng.normal(0, 0.01, (h, w))
    z[100:160, 150:200] = np.nan  # a shadow
    return z, np.isfinite(z)


def test_injected_stripes_and_spikes_are_removed_true_points_kept() -> None:
    z, truth = _surface()
    out = z.copy()
    injected = np.zeros_like(truth)
    # Stripes hugging the shadow border (2 px wide, 60 px long, 3 mm off) and one 1-px stripe elsewhere.
    out[100:160, 150:152] = z[99, 150] + 3.0
    injected[100:160, 150:152] = True
    out[30, 20:120] = 90.0
    injected[30, 20:120] = True
    truth[30, 20:120] = False
    # Isolated spikes and small blobs.
    rng = np.random.default_rng(5)
    iy, ix = rng.integers(0, 240, 300), rng.integers(0, 320, 300)
    ok = ~((iy >= 100) & (iy < 160) & (ix >= 150) & (ix < 200)) & (iy != 30)
    out[iy[ok], ix[ok]] += rng.choice([-1, 1], ok.sum()) * rng.uniform(2, 10, ok.sum())
    injected[iy[ok], ix[ok]] = True
    truth[iy[ok], ix[ok]] = False
    out[200:204, 250:255] -= 4.0  # a 4x5 blob
    injected[200:204, 250:255] = True
    truth[200:204, 250:255] = False

    res = link_cluster(out, link_mm=0.3, min_cluster_px=50, stripe_width_px=2)
    assert not res.keep[injected].any()
    assert res.keep[truth].mean() >= 0.999
    assert res.removed_stripes >= 120  # the 2-px shadow stripe is one large but thin cluster


def test_points_map_uses_depth_channel() -> None:
    z, truth = _surface(60, 80)
    pts = np.dstack([np.zeros_like(z), np.zeros_like(z), z])
    pts[10, 10, 2] += 5.0
    res = link_cluster(pts, link_mm=0.2, min_cluster_px=20)
    assert not res.keep[10, 10] and res.keep[truth].sum() == truth.sum() - 1


def test_labels_match_opencv_on_the_doubled_link_grid() -> None:
    """Independent labelling: OpenCV on a grid with the links drawn as pixels between the nodes."""
    import cv2

    z, _ = _surface(80, 100)
    z[20:40, 30:60] += 1.0  # a raised block: not linked to its surroundings at 0.3 mm
    z[50, :] = np.nan
    res = link_cluster(z, link_mm=0.3, min_cluster_px=1)
    H, W = z.shape
    grid = np.zeros((2 * H - 1, 2 * W - 1), np.uint8)
    grid[::2, ::2] = np.isfinite(z)
    with np.errstate(invalid="ignore"):
        grid[::2, 1::2] = np.abs(np.diff(z, axis=1)) < 0.3
        grid[1::2, ::2] = np.abs(np.diff(z, axis=0)) < 0.3
    ref = cv2.connectedComponents(grid, connectivity=4, ltype=cv2.CV_32S)[1][::2, ::2]
    pairs = np.unique(np.column_stack([res.labels.ravel(), ref.ravel()]), axis=0)
    assert len(pairs) == len(np.unique(ref)) >= 4  # a one-to-one map between the two labellings
    assert len(np.unique(pairs[:, 0])) == len(pairs)


def test_depth_edges_are_the_rim_of_a_step_not_a_steep_continuous_surface() -> None:
    """A sheet 30 mm above the table ending at column 50, with a mixed pixel column at the edge 0.3 mm below
    the sheet (what a blend of the two codes gives), beside a continuous 70-degree slope (1.1 mm per 2 px on
    the demo camera) and a shadow (invalid) patch on the sheet."""
    z = np.full((40, 100), 430.0)  # the table, 430 mm from the camera
    z[:, :50] = 400.0  # the sheet
    z[:, 49] = 400.3  # mixed pixels at its edge
    slope = 400.0 + 0.55 * np.arange(30)  # 0.55 mm per pixel
    z[:10, 60:90] = slope
    z[20:30, 10:20] = np.nan  # shadow
    edges = depth_edges(z, jump_mm=3.0)
    assert edges[:, 49].all() and edges[:, 50].all()  # the mixed pixel and the table pixel beside it
    shadow_rim = np.zeros_like(edges)
    shadow_rim[19:31, 9:21] = True
    shadow_rim[20:30, 10:20] = False
    assert edges[shadow_rim].all()  # the pixels around the shadow
    rest_of_sheet = np.ones_like(edges)
    rest_of_sheet[19:31, 9:21] = False
    rest_of_sheet[:, 48:] = False
    assert not edges[rest_of_sheet].any()
    assert not edges[:9, 61:89].any()  # the steep slope is continuous (its rim on the table is a step)
    assert not edges[np.isnan(z)].any()
    assert not edges[0, :48].any()  # the image border is not a rim


def test_depth_edges_refuse_a_bad_map() -> None:
    with pytest.raises(ConfigError, match="depth map"):
        depth_edges(np.zeros((4, 4, 3)), 3.0)
    with pytest.raises(ConfigError, match="jump"):
        depth_edges(np.zeros((4, 4)), 0.0)
