"""Link-clustering outlier filter on organised height maps (dissertation 4.4).

Two 4-neighbour pixels are *linked* when both are valid and their heights differ by less than the link
distance (0.1-0.5 mm). Clusters are the connected components of the link graph. Clusters smaller than
``min_cluster_px`` are outliers (pulse noise, dark spots); so are thin stripes -- clusters with no pixel whose
whole (2 * stripe_width_px + 1)^2 window belongs to the same cluster -- the outlier rims left at shadow
borders. Heights are never modified, so real dents stay visible.

The link graph is labelled by OpenCV on a doubled grid: node (i, j) sits at (2i, 2j), the link between two
horizontal or vertical neighbours at the cell between them, so 4-connected labelling of that image gives
exactly the link components (no union-find by hand; OpenCV's labelling is the fastest at hand).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError


@dataclass(frozen=True)
class LinkFilterResult:
    """``keep``: (H, W) bool of points kept; ``labels``: cluster id per pixel (0 for invalid);
    counts of points removed as small clusters and as stripes."""

    keep: NDArray[np.bool_]
    labels: NDArray[np.int32]
    removed_small: int
    removed_stripes: int


def link_cluster(
    height_map: NDArray[np.floating],
    link_mm: float = 0.3,
    min_cluster_px: int = 200,
    stripe_width_px: int = 2,
) -> LinkFilterResult:
    """Filter an organised map: (H, W) heights or (H, W, 3) points (z used as depth), NaN where invalid (mm)."""
    z = np.asarray(height_map)
    if z.ndim == 3 and z.shape[2] == 3:
        z = z[..., 2]
    if z.ndim != 2:
        raise ConfigError(f"link_cluster: expected an (H, W) or (H, W, 3) map, got shape {z.shape}")
    if not link_mm > 0:
        raise ConfigError(f"link_cluster: link distance must be > 0 mm, got {link_mm}")
    z = z.astype(np.float32, copy=False)
    H, W = z.shape
    valid = np.isfinite(z)
    grid = np.zeros((2 * H - 1, 2 * W - 1), np.uint8)
    grid[::2, ::2] = valid
    with np.errstate(invalid="ignore"):
        grid[::2, 1::2] = np.abs(z[:, 1:] - z[:, :-1]) < link_mm  # NaN compares False: no link
        grid[1::2, ::2] = np.abs(z[1:, :] - z[:-1, :]) < link_mm
    n, lab2 = cv2.connectedComponents(grid, connectivity=4, ltype=cv2.CV_32S)
    labels = np.ascontiguousarray(lab2[::2, ::2])
    size = np.bincount(labels.ravel(), minlength=n)
    big = size >= min_cluster_px
    big[0] = False
    # Stripe test: a pixel is interior when its whole window holds one label (min == max over the window).
    k = np.ones((2 * stripe_width_px + 1,) * 2, np.uint8)
    labf = labels.astype(np.float32)  # labels < 2^24 are exact in float32 (cv2 morphology has no int32)
    interior = (cv2.erode(labf, k, borderType=cv2.BORDER_REPLICATE) == cv2.dilate(labf, k)) & (labels > 0)
    has_interior = np.bincount(labels[interior], minlength=n) > 0
    good = big & has_interior
    keep = good[labels]
    removed_small = int(size[1:][~big[1:]].sum())
    removed_stripes = int(size[big & ~has_interior].sum())
    return LinkFilterResult(
        keep=keep, labels=labels, removed_small=removed_small, removed_stripes=removed_stripes
    )
