"""Statistical process control of one recipe from the results database: per run, the mean and the extreme
deviation of the whole part and of each of the recipe's regions, in time order, and the capability of the
mean against the tolerance band.

The sample: one value per run, the run's mean signed deviation (mm) of the part or the region, over the
runs of the recipe that finished with a ``pass`` or ``fail`` verdict (``incomplete`` runs measured too
little to judge). With x̄ and s the mean and the sample standard deviation (n - 1) of these values and
[L, U] the tolerance band of the newest run:

    Cp = (U - L) / (6 s)        Cpk = min(U - x̄, x̄ - L) / (3 s)

This is the capability of where the surface sits from part to part (s is the overall spread, no rational
subgroups: Pp/Ppk in AIAG terms). It does not judge the scatter of the points within one part; the extreme
deviation's trend shows that. Cp and Cpk are None with fewer than two runs or no spread.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from datetime import datetime

PART = ""  # the series name of the whole part


@dataclass(frozen=True)
class TrendPoint:
    """One run's figures in a series (mm): mean, min, max and the extreme (min or max, whichever is
    farther from zero, signed)."""

    folder: str
    started: datetime
    serial: str | None
    verdict: str | None
    mean_mm: float | None
    min_mm: float | None
    max_mm: float | None

    @property
    def extreme_mm(self) -> float | None:
        if self.min_mm is None or self.max_mm is None:
            return self.max_mm if self.min_mm is None else self.min_mm
        return self.max_mm if abs(self.max_mm) >= abs(self.min_mm) else self.min_mm


@dataclass(frozen=True)
class Capability:
    """Cp and Cpk of the per-run means of a series (see the module's docstring), band in mm."""

    n: int
    mean_mm: float | None
    std_mm: float | None
    lower_mm: float | None
    upper_mm: float | None
    cp: float | None
    cpk: float | None


@dataclass(frozen=True)
class SpcSeries:
    """The whole part (``name`` ``""``) or one region: its trend (oldest first) and capability."""

    name: str
    trend: list[TrendPoint]
    capability: Capability


@dataclass(frozen=True)
class Spc:
    """SPC of one recipe: the runs counted, the whole part's series and one series per region."""

    recipe: str
    n_runs: int
    part: SpcSeries
    regions: list[SpcSeries]

    @property
    def series(self) -> list[SpcSeries]:
        return [self.part, *self.regions]


def capability(means: list[float], lower: float | None, upper: float | None) -> Capability:
    """Cp/Cpk of ``means`` against [lower, upper] (mm)."""
    n = len(means)
    if n == 0:
        return Capability(0, None, None, lower, upper, None, None)
    xbar = math.fsum(means) / n
    if n < 2:
        return Capability(n, xbar, None, lower, upper, None, None)
    s = math.sqrt(math.fsum((x - xbar) ** 2 for x in means) / (n - 1))
    if s <= 0 or lower is None or upper is None:
        return Capability(n, xbar, s, lower, upper, None, None)
    return Capability(
        n, xbar, s, lower, upper, (upper - lower) / (6 * s), min(upper - xbar, xbar - lower) / (3 * s)
    )


def series(name: str, trend: list[TrendPoint], lower: float | None, upper: float | None) -> SpcSeries:
    means = [p.mean_mm for p in trend if p.mean_mm is not None]
    return SpcSeries(name, trend, capability(means, lower, upper))


TREND_COLUMNS = (
    "series",
    "folder",
    "started_utc",
    "serial",
    "verdict",
    "mean_mm",
    "min_mm",
    "max_mm",
    "extreme_mm",
)
CAPABILITY_COLUMNS = ("series", "n", "mean_mm", "std_mm", "lower_mm", "upper_mm", "cp", "cpk")


def _name(s: SpcSeries) -> str:
    return "part" if s.name == PART else f"region:{s.name}"


def _cell(value: object) -> object:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, datetime):
        return value.isoformat(timespec="seconds")
    return "" if value is None else value


def to_csv(spc: Spc, table: str = "trend") -> str:
    """``trend``: one row per run and series (mm); ``capability``: one row per series."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    if table == "trend":
        w.writerow(TREND_COLUMNS)
        for s in spc.series:
            for p in s.trend:
                values = (
                    _name(s),
                    p.folder,
                    p.started,
                    p.serial,
                    p.verdict,
                    p.mean_mm,
                    p.min_mm,
                    p.max_mm,
                    p.extreme_mm,
                )
                w.writerow([_cell(v) for v in values])
    elif table == "capability":
        w.writerow(CAPABILITY_COLUMNS)
        for s in spc.series:
            c = s.capability
            w.writerow(
                [_cell(v) for v in (_name(s), c.n, c.mean_mm, c.std_mm, c.lower_mm, c.upper_mm, c.cp, c.cpk)]
            )
    else:
        raise ValueError(f"unknown SPC table {table!r}: trend or capability")
    return out.getvalue()
