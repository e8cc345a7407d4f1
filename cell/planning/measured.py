"""The measured-view record the feedback planner consumes, and how to build it from per-pixel masks.

Whatever produces a view (the scan pipeline, or the simulator's ground truth with a glare criterion in tests)
hands over: the camera pose, the measured points in {W}, and per reason (shadow, glare, low contrast) a
mask of pixels that gave no point together with each pixel's *nominal* surface point (the camera ray cast on
the CAD).
Each connected masked region becomes a :class:`DefectRegion` whose boundary points form the shadow map IS or
the reflection map IR (eqs 3.7-3.8).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.geometry import Pose

Array = NDArray[np.float64]
MAX_REGION_POINTS = 2000  # region interiors are subsampled to this many points (deterministic stride)


@dataclass(frozen=True)
class DefectRegion:
    """One connected hole region of one view: its reason, boundary points and (subsampled) interior points."""

    reason: str
    boundary_W: Array
    points_W: Array
    pixels: int


@dataclass(frozen=True)
class MeasuredView:
    """A measured view: camera pose, measured points (world mm), their unit normals when the producer knows
    them (else None), its defect regions, each point's signed deviation from the nominal (mm) when known:
    two views that measure the same spot must agree on it, whatever the surface's curvature; each point's
    standard uncertainty (mm, cell.analysis.uncertainty) when known; and, with the deviations, the nominal's
    unit normal at each point (its closest nominal triangle's, {W}) when the producer found it."""

    T_W_C: Pose
    points_W: Array
    defects: list[DefectRegion] = field(default_factory=list)
    normals_W: Array | None = None
    deviation_mm: NDArray[np.float64] | None = None
    uncertainty_mm: NDArray[np.floating] | None = None
    nominal_normals_W: Array | None = None


def defect_regions(
    mask: NDArray[np.bool_], nominal_W: Array, reason: str, min_pixels: int
) -> list[DefectRegion]:
    """Connected regions (8-connected, OpenCV) of ``mask`` with at least ``min_pixels`` pixels whose nominal
    point is known; the boundary is the region minus its 3x3 erosion."""
    m = (mask & np.isfinite(nominal_W).all(axis=-1)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    eroded = cv2.erode(m, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    edge = m.astype(bool) & ~eroded.astype(bool)
    out = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < min_pixels:
            continue
        # within the region's bounding box (row-major there is row-major in the image: the same points in
        # the same order), not over the whole image once per region (a view has tens of regions)
        x, y, w, h = (int(v) for v in stats[k, :4])
        box = np.s_[y : y + h, x : x + w]
        inside = lab[box] == k
        nominal = nominal_W[box]
        pts = nominal[inside]
        stride = max(1, len(pts) // MAX_REGION_POINTS)
        out.append(DefectRegion(reason, nominal[inside & edge[box]], pts[::stride], int(inside.sum())))
    return out


def measured_view_from_masks(
    T_W_C: Pose,
    points_W: Array,
    valid: NDArray[np.bool_],
    reason_masks: dict[str, NDArray[np.bool_]],
    nominal_W: Array,
    min_region_px: int = 20,
    normals_W: Array | None = None,
) -> MeasuredView:
    """Build the record from image-shaped arrays: ``points_W`` (H, W, 3) with ``valid`` (H, W) measured
    pixels, per-reason masks (H, W) and the nominal surface point of every pixel (H, W, 3; NaN off the
    part)."""
    regions: list[DefectRegion] = []
    for reason, mask in reason_masks.items():
        regions += defect_regions(mask, nominal_W, reason, min_region_px)
    normals = None if normals_W is None else normals_W[valid].reshape(-1, 3)
    return MeasuredView(np.asarray(T_W_C, dtype=np.float64), points_W[valid].reshape(-1, 3), regions, normals)
