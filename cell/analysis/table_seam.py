"""The table at the part's foot, cropped again once the cloud is aligned (issue 17).

Each view is cropped at the table in {W} (:class:`cell.analysis.crop.PartCrop`: points less than the margin
above z = 0), at the view's kinematic pose. Where that pose is off by more than the margin (a view tilted
0.02 deg lifts the table 0.2 mm at 500 mm from the camera axis; an uncalibrated cell's poses are off by 1 mm),
table points beside the part pass that crop, merge into the cloud and, once the recipe's alignment has put
the part where its datums say, lie on the table plane beside the walls' foot: gross errors of up to the crop's
5 mm that no per-point uncertainty describes. In the aligned part frame the table is where the part stands
on it (world z = 0 carried into {P} by the recipe's placement T_W_P), so the same margin applied there finds
them; so does, a little higher, a table point the decode lifted past the margin: it lies outside the part by
more than its height above the table (nearer the table than the part). Real wall points above the margin
stay (their distance to the nominal is the measurement's noise); a real bulge of the wall's lowest
millimetres, more than its height outward, would be cut with the table. Millimetres.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.analysis.errormap import NominalMesh, signed_distance

# above the margin, a point this near the table that lies outside the part by more than its height is table
SEAM_BAND_MM = 2.0


def above_table_mm(points_P: NDArray[np.float64], T_W_P: NDArray[np.float64]) -> NDArray[np.float64]:
    """Height (mm) of each point of ``points_P`` (N, 3, part frame) above the table top, the plane z = 0 of
    {W} carried into {P} by the part's placement ``T_W_P``."""
    T = np.asarray(T_W_P, dtype=np.float64)
    p = np.asarray(points_P, dtype=np.float64).reshape(-1, 3)
    return np.asarray(p @ T[2, :3] + T[2, 3], dtype=np.float64)  # z of the point in {W}


def table_seam(
    points_P: NDArray[np.float64],
    T_W_P: NDArray[np.float64],
    margin_mm: float,
    nominal_P: NominalMesh,
    band_mm: float = SEAM_BAND_MM,
    deviation_mm: NDArray[np.float64] | None = None,
) -> NDArray[np.bool_]:
    """Which points of the aligned cloud ``points_P`` (N, 3, {P}) are table: those less than ``margin_mm``
    above it (:func:`above_table_mm`), and those less than ``band_mm`` above it that lie outside the nominal
    ``nominal_P`` by more than their height (nearer the table than the part: a table point the decode lifted
    past the margin). ``deviation_mm``: the points' signed distances to ``nominal_P`` when the caller has
    them (else computed for the band's points)."""
    h = above_table_mm(points_P, T_W_P)
    table = h < margin_mm
    band = np.flatnonzero(~table & (h < band_mm))
    if len(band):
        if deviation_mm is None:
            dev = signed_distance(nominal_P, points_P[band]).deviation_mm
        else:
            dev = deviation_mm[band]
        table[band] = dev > h[band]
    return table


def crop_table_seam(
    points_P: NDArray[np.float64],
    u_mm: NDArray[np.float64] | None,
    T_W_P: NDArray[np.float64],
    margin_mm: float,
    nominal_P: NominalMesh,
    band_mm: float = SEAM_BAND_MM,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, int]:
    """The aligned cloud ``points_P`` (N, 3, {P}) and its points' uncertainty ``u_mm`` (N,) without the table
    (:func:`table_seam`). Returns both and how many were cut."""
    keep = ~table_seam(points_P, T_W_P, margin_mm, nominal_P, band_mm)
    return points_P[keep], (None if u_mm is None else u_mm[keep]), int((~keep).sum())
