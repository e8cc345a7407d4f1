"""Decision rules: which points conform, which do not, and which the measurement cannot decide.

``simple`` (the default, the cell's rule before issue 17): a point conforms when its deviation lies within its
tolerance band, as if it were exact. ``guarded`` (ISO 14253-1, ASME B89.7.3.1 guard bands): with the point's
expanded uncertainty U = k u (``k`` the coverage factor, 2 by default),

* it **conforms** when its deviation lies in the band shrunk by U on both sides (the conformance zone);
* it **does not conform** when it lies outside the band widened by U (the non-conformance zone);
* else it is **ambiguous**: the measurement cannot tell whether the part is within its tolerance there.

A band narrower than 2U has no conformance zone: nothing there can be shown to conform. What ambiguous points
make of the verdict is the recipe's (``guard_band.ambiguous``): ``fail`` (the customer's side of ISO 14253-1:
not proven in tolerance), ``pass`` (the supplier's: not proven out of tolerance) or ``incomplete`` (measure
again, better). Regions and the verdict follow from the points (:func:`cell.analysis.report.summarise`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from cell.analysis.regions import PointBands, Tolerance

CONFORM, AMBIGUOUS, NONCONFORM = 0, 1, 2
CLASS_NAMES = ("conform", "ambiguous", "nonconform")

Rule = Literal["simple", "guarded"]
AmbiguousVerdict = Literal["fail", "pass", "incomplete"]


@dataclass(frozen=True)
class DecisionRule:
    """How points are decided: ``rule``, the coverage factor ``k`` of U = k u, and what ``ambiguous`` points
    make of a verdict."""

    rule: Rule = "simple"
    k: float = 2.0
    ambiguous: AmbiguousVerdict = "incomplete"

    def guard_mm(self, n_points: int, uncertainty_mm: NDArray[np.floating] | None) -> NDArray[np.float64]:
        """U (mm) of every point: k u under the guarded rule, 0 under the simple one. The guarded rule needs
        the points' uncertainties: without them (a cloud measured elsewhere) it cannot be applied."""
        if self.rule == "simple":
            return np.zeros(n_points)
        if uncertainty_mm is None:
            raise ValueError("the guarded decision rule needs each point's uncertainty; this cloud has none")
        u = np.asarray(uncertainty_mm, dtype=np.float64)
        if u.shape != (n_points,):
            raise ValueError(f"{u.shape} uncertainties for {n_points} points")
        # a point whose uncertainty is not known cannot be shown to conform
        return np.where(np.isfinite(u), self.k * u, np.inf)

    def to_json(self) -> dict[str, object]:
        return {"rule": self.rule, "k": self.k, "ambiguous": self.ambiguous}


def _per_point(band: Tolerance | PointBands, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if isinstance(band, Tolerance):
        return np.full(n, band.lower_mm), np.full(n, band.upper_mm)
    return np.asarray(band.lower_mm, np.float64), np.asarray(band.upper_mm, np.float64)


def widened(band: Tolerance | PointBands, guard_mm: NDArray[np.floating]) -> Tolerance | PointBands:
    """The band widened by U on both sides: a deviation beyond it does not conform (``band`` itself when U
    is 0 everywhere: the simple rule)."""
    if not np.any(guard_mm):
        return band
    lo, hi = _per_point(band, len(guard_mm))
    return PointBands(lo - guard_mm, hi + guard_mm)


def shrunk(band: Tolerance | PointBands, guard_mm: NDArray[np.floating]) -> Tolerance | PointBands:
    """The band shrunk by U on both sides (the conformance zone; empty where U exceeds half the band;
    ``band`` itself when U is 0 everywhere: the simple rule)."""
    if not np.any(guard_mm):
        return band
    lo, hi = _per_point(band, len(guard_mm))
    return PointBands(lo + guard_mm, hi - guard_mm)


def classify(
    deviation_mm: NDArray[np.floating], band: Tolerance | PointBands, guard_mm: NDArray[np.floating]
) -> NDArray[np.int8]:
    """CONFORM, AMBIGUOUS or NONCONFORM (int8) of every point."""
    d = np.asarray(deviation_mm, dtype=np.float64)
    out = np.full(len(d), AMBIGUOUS, np.int8)
    out[~shrunk(band, guard_mm).outside(d)] = CONFORM
    out[widened(band, guard_mm).outside(d)] = NONCONFORM
    return out


def class_counts(classes: NDArray[np.integer]) -> dict[str, int]:
    """How many points each class holds."""
    counts = np.bincount(np.asarray(classes, dtype=np.int64), minlength=3)
    return {name: int(c) for name, c in zip(CLASS_NAMES, counts, strict=True)}
