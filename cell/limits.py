"""Plausibility limits of tolerance bands (mm), shared by the recipe schema (:mod:`cell.config`) and ``cell
compare --tolerance``; a module without imports, so that the command checks its option without loading the
config schemas (pydantic)."""

from __future__ import annotations

MAX_TOLERANCE_MM = 50.0  # a band wider than this is not a tolerance
MIN_TOLERANCE_MM = 0.001  # a limit closer to zero than 1 um (but not zero) is a value in metres


def tolerance_problem(*limits_mm: float) -> str | None:
    """What is implausible about tolerance limits in mm, or None: a limit beyond +-50 mm, or one nearer to
    zero than 0.001 mm without being zero (-0.0003 is a band of 0.3 mm written in metres). Zero itself is a
    one-sided band's limit."""
    for v in limits_mm:
        if abs(v) > MAX_TOLERANCE_MM:
            return f"{v:g} mm is not a plausible tolerance (units are mm)"
        if 0 < abs(v) < MIN_TOLERANCE_MM:
            return f"{v:g} mm is below 1 um: a tolerance in metres? (units are mm; {v:g} m = {v * 1000:g} mm)"
    return None
