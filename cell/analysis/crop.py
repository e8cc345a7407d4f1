"""What of a measured cloud is the part: points on the table and background far from the nominal are not.

One rule for every measured cloud: the inspection crops each view with it (world frame, the table top is the
plane z = 0) and ``cell compare`` crops a cloud from elsewhere with it (the nominal's frame, the table where
the part stands). Millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class CropMasks:
    """Per point: on the table, or background (farther from the nominal than the crop, off the table)."""

    on_table: NDArray[np.bool_]
    background: NDArray[np.bool_]

    @property
    def part(self) -> NDArray[np.bool_]:
        """The points that are the part: neither table nor background."""
        return ~self.on_table & ~self.background

    def counts(self) -> dict[str, int]:
        """Points left out, by reason (``table``, ``background``), as the report's ``excluded`` counts."""
        return {"table": int(self.on_table.sum()), "background": int(self.background.sum())}


@dataclass(frozen=True)
class PartCrop:
    """Points less than ``table_margin_mm`` above the table top ``z = table_z_mm`` (frame of the points;
    None: no table) are the table; points farther than ``background_mm`` from the nominal surface are
    background (None: none is)."""

    table_z_mm: float | None = 0.0
    table_margin_mm: float = 0.5
    background_mm: float | None = 5.0

    def on_table(self, points_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which of ``points_mm`` (N, 3) are the table (all False without one)."""
        if self.table_z_mm is None:
            return np.zeros(len(points_mm), dtype=bool)
        return np.asarray(points_mm)[:, 2] < self.table_z_mm + self.table_margin_mm

    def split(self, points_mm: NDArray[np.float64], deviation_mm: NDArray[np.float64]) -> CropMasks:
        """Which of ``points_mm`` (N, 3) with signed deviations ``deviation_mm`` (N,) are table and
        background (the table's points' deviations are not read)."""
        n = len(deviation_mm)
        on_table = self.on_table(points_mm)
        far = (
            np.zeros(n, dtype=bool)
            if self.background_mm is None
            else np.abs(deviation_mm) > self.background_mm
        )
        return CropMasks(on_table, far & ~on_table)
