"""Statistical process control of one recipe from the results database: per run, the mean and the extreme
deviation of the whole part and of each of the recipe's regions, in time order, and the capability of the
mean against the tolerance band.

The sample: one value per run, the run's mean signed deviation (mm) of the part or the region, over the
runs of the recipe that finished with a ``pass`` or ``fail`` verdict (``incomplete`` runs measured too
little to judge), in time order. They are individual values (one part a subgroup), so as on an
individuals chart (AIAG SPC manual, 2nd ed.) the short-term spread comes from the moving ranges of
consecutive runs and the long-term spread from all of them. With x̄ the mean, MR̄ the mean of |x_i - x_(i-1)|,
sigma_within = MR̄ / d2 (d2 = 1.128 for ranges of two), s the sample standard deviation (n - 1) and [L, U]
the tolerance band of the newest run:

    Cp = (U - L) / (6 sigma_within)        Cpk = min(U - x̄, x̄ - L) / (3 sigma_within)
    Pp = (U - L) / (6 s)                   Ppk = min(U - x̄, x̄ - L) / (3 s)

Cp/Cpk say what the process could do if it stayed as steady as from one run to the next; Pp/Ppk what it did
over the whole series (a drift lowers Pp below Cp). This is the capability of where the surface sits from
part to part; it does not judge the scatter of the points within one part (the extreme deviation's trend
shows that). The indices are None with fewer than two runs or no spread.
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
    """Cp/Cpk (short-term spread ``sigma_within_mm``) and Pp/Ppk (overall ``std_mm``) of the per-run means of
    a series (see the module's docstring), band in mm."""

    n: int
    mean_mm: float | None
    std_mm: float | None
    lower_mm: float | None
    upper_mm: float | None
    cp: float | None
    cpk: float | None
    sigma_within_mm: float | None = None
    pp: float | None = None
    ppk: float | None = None


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


D2_RANGE_OF_TWO = 1.128  # d2 of a range of two values: E[|x1 - x2|] = d2 sigma for normal x


def _indices(
    xbar: float, sigma: float, lower: float | None, upper: float | None
) -> tuple[float | None, float | None]:
    """(U - L) / 6 sigma and min(U - x̄, x̄ - L) / 3 sigma, or None without a band or a spread."""
    if sigma <= 0 or lower is None or upper is None:
        return None, None
    return (upper - lower) / (6 * sigma), min(upper - xbar, xbar - lower) / (3 * sigma)


def capability(means: list[float], lower: float | None, upper: float | None) -> Capability:
    """Cp/Cpk and Pp/Ppk of ``means`` (in time order) against [lower, upper] (mm)."""
    n = len(means)
    if n == 0:
        return Capability(0, None, None, lower, upper, None, None)
    xbar = math.fsum(means) / n
    if n < 2:
        return Capability(n, xbar, None, lower, upper, None, None)
    s = math.sqrt(math.fsum((x - xbar) ** 2 for x in means) / (n - 1))
    within = math.fsum(abs(b - a) for a, b in zip(means, means[1:])) / (n - 1) / D2_RANGE_OF_TWO
    cp, cpk = _indices(xbar, within, lower, upper)
    pp, ppk = _indices(xbar, s, lower, upper)
    return Capability(n, xbar, s, lower, upper, cp, cpk, within, pp, ppk)


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
CAPABILITY_COLUMNS = (  # after "series", the names of Capability's fields
    "series",
    "n",
    "mean_mm",
    "std_mm",
    "lower_mm",
    "upper_mm",
    "cp",
    "cpk",
    "sigma_within_mm",
    "pp",
    "ppk",
)


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
            w.writerow([_name(s), *(_cell(getattr(c, column)) for column in CAPABILITY_COLUMNS[1:])])
    else:
        raise ValueError(f"unknown SPC table {table!r}: trend or capability")
    return out.getvalue()
