"""Black marker dots in a back image: segmentation, intensity-weighted centroid (eq 2.14), identification.

Why black dots (2.5, Figs 2.20-2.22): the image is the sum of the top-skin reflection and a weaker, offset
bottom-skin copy. Where a top dot is, only the bottom copy of the white screen shines (level R_b / (R_t + R_b)
of the background); where a bottom dot is, the top skin still reflects white (level R_t / (R_t + R_b)). With
R_b < R_t the top dots are the darker ones, so a threshold at ``dark_fraction`` of the local background keeps
them and drops the bottom copies. The centroid weights each pixel by how far it lies below that threshold
(eq 2.14 with I_m = the threshold level), so the bottom copy's pixels, which lie above it, get no weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class DotDetections:
    """Dots found in one image: sub-pixel centroids (N, 2) as (u, v) = (column, row), pixel count and depth
    (1 - darkest / local background)."""

    centroids_px: NDArray[np.float64]
    area_px: NDArray[np.int64]
    depth: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.centroids_px)


def local_background(image: NDArray, window_px: int) -> NDArray[np.float32]:
    """Bright level around every pixel: a grey-scale closing-like max filter (removes dots narrower than the
    window) followed by a box blur of the same size to smooth the noise it picks up."""
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (window_px, window_px))
    bright = cv2.dilate(image.astype(np.float32), k)
    return np.asarray(cv2.blur(bright, (window_px, window_px)), np.float32)


def detect_dots(
    image: NDArray,
    dark_fraction: float = 0.5,
    window_px: int = 25,
    min_area_px: int = 4,
    max_area_px: int = 2000,
    min_background: float = 20.0,
    full_profile_px: int = 0,
) -> DotDetections:
    """Find dark dots on a bright background and their intensity-weighted centroids (eq 2.14).

    A pixel belongs to a dot when it is below ``dark_fraction`` of the local background (``window_px`` must
    exceed twice a dot's diameter in pixels) and that background is above ``min_background`` (DN; excludes
    the unlit surroundings). Components outside [min_area_px, max_area_px] are dropped.

    ``full_profile_px`` = 0: eq 2.14 with I_m at the threshold, so only pixels below it weigh (needed on
    glass, where the bottom copy's pixels lie just above it). > 0: I_m = the local background over the dot
    grown by that many pixels, so the whole blurred edge weighs; cutting the profile at the threshold biases
    the centroid by the dot's sub-pixel phase (0.028 px median on the simulated board, 0.007 px with 1 px of
    growth), a bias that averaging frames does not remove. For images without a second reflection.
    """
    img = image.astype(np.float32)
    bg = local_background(img, window_px)
    thr = dark_fraction * bg
    mask = ((img < thr) & (bg > min_background)).astype(np.uint8)
    n, labels_cv, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    labels = np.asarray(labels_cv, np.int32)  # CV_32S already: no copy
    if full_profile_px > 0:  # grey dilation of the label image grows every (well separated) dot
        k = np.ones((2 * full_profile_px + 1,) * 2, np.uint8)
        grown = cv2.dilate(labels.astype(np.float32), k).astype(np.int64)
        rows, cols = np.nonzero(grown)
        lab: NDArray[np.signedinteger] = grown[rows, cols]
        w = np.clip(bg - img, 0, None)[rows, cols].astype(np.float64)
    else:
        rows, cols = np.nonzero(labels)
        lab = labels[rows, cols]
        w = (thr - img)[rows, cols].astype(np.float64)  # eq 2.14: weight I_m - I_i, I_m at the threshold
    sw = np.bincount(lab, w, minlength=n)
    cu = np.bincount(lab, w * cols, minlength=n) / np.where(sw > 0, sw, 1)
    cv = np.bincount(lab, w * rows, minlength=n) / np.where(sw > 0, sw, 1)
    rows, cols = np.nonzero(labels)
    lab = labels[rows, cols]
    darkest = np.full(n, np.inf)
    np.minimum.at(darkest, lab, (img / np.maximum(bg, 1e-6))[rows, cols])
    area = stats[:, cv2.CC_STAT_AREA]
    # components touching the unlit border of the pane are cut dots: their centroids would be biased
    x0, y0 = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[:, cv2.CC_STAT_WIDTH], y0 + stats[:, cv2.CC_STAT_HEIGHT]
    dark_around = cv2.erode((bg > min_background).astype(np.uint8), np.ones((3, 3), np.uint8)) == 0
    touches = np.bincount(lab, dark_around[rows, cols], minlength=n) > 0
    keep = (area >= min_area_px) & (area <= max_area_px) & (sw > 0) & ~touches
    keep &= (x0 > 0) & (y0 > 0) & (x1 < image.shape[1]) & (y1 < image.shape[0])
    keep[0] = False
    return DotDetections(np.column_stack([cu, cv])[keep], area[keep].astype(np.int64), 1 - darkest[keep])


def identify(
    predicted_mm: NDArray[np.float64], dots_mm: NDArray[np.float64], gate_mm: float
) -> NDArray[np.int64]:
    """Which dot each detection is: the dot nearest to the detection's predicted plane position (N, 2), if
    within ``gate_mm``; -1 otherwise. When several detections claim one dot only the closest keeps it."""
    ids = np.full(len(predicted_mm), -1, dtype=np.int64)
    finite = np.all(np.isfinite(predicted_mm), axis=1)
    if not np.any(finite) or len(dots_mm) == 0:
        return ids
    d_all, i_all = cKDTree(dots_mm).query(predicted_mm[finite], distance_upper_bound=gate_mm)
    found = np.isfinite(d_all)
    cand = np.flatnonzero(finite)[found]
    idx, dist = np.asarray(i_all)[found], np.asarray(d_all)[found]
    order = np.argsort(dist)  # closest claims first; later (farther) claims of the same dot are dropped
    _, first = np.unique(idx[order], return_index=True)
    win = order[first]
    ids[cand[win]] = idx[win]
    return ids
