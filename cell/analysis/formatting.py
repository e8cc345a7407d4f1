"""Numbers as the report prints them for people: fixed decimals by quantity, a true minus sign, thin spaces
between thousands, ages and times in the units a person reads.

Deviations in mm to the micrometre (3 decimals: the sensor's noise is tens of micrometres, more digits are
noise), coordinates to 0.1 mm, counts whole with thousands separated, fractions as percent.
"""

from __future__ import annotations

from datetime import UTC, datetime

MINUS = "\u2212"
THIN = "\u202f"  # narrow no-break space: 1 234 567 (SI brochure: groups of three, no commas or points)


def _unsigned_zero(value: float, digits: int) -> float:
    """0.0 for a value that rounds to zero (no "−0.000")."""
    return 0.0 if round(value, digits) == 0 else value


def signed(value: float, digits: int = 3) -> str:
    """+0.300 / −0.598 / 0.000: a sign except on zero, a true minus."""
    value = _unsigned_zero(value, digits)
    return f"{value:+.{digits}f}".replace("-", MINUS) if value else f"{0:.{digits}f}"


def number(value: float, digits: int = 3) -> str:
    """0.030 / −0.598: a sign only when negative."""
    return f"{_unsigned_zero(value, digits):.{digits}f}".replace("-", MINUS)


def mm(value: float | None, digits: int = 3, sign: bool = True) -> str:
    """A length or deviation in mm: ``−0.598 mm``; ``–`` when unknown."""
    if value is None:
        return "\u2013"
    return f"{signed(value, digits) if sign else number(value, digits)} mm"


def count(n: int | None) -> str:
    """1 234 567 (thin spaces); ``–`` when unknown."""
    return "\u2013" if n is None else f"{int(n):,}".replace(",", THIN)


def percent(fraction: float | None, digits: int = 1) -> str:
    """0.98234 -> 98.2 %; ``–`` when unknown."""
    return "\u2013" if fraction is None else f"{100 * fraction:.{digits}f}{THIN}%"


def point(xyz: list[float] | tuple[float, ...], digits: int = 1) -> str:
    """(12.3, −4.0, 55.1) in mm."""
    return "(" + ", ".join(number(c, digits) for c in xyz) + ")"


def age(days: float | None) -> str:
    """An age a person reads: 40 s, 12 min, 5.2 h, 3.4 days, 41 days."""
    if days is None:
        return "\u2013"
    s = days * 86400.0
    if s < 90:
        return f"{s:.0f}{THIN}s"
    if s < 5400:
        return f"{s / 60:.0f}{THIN}min"
    if days < 2:
        return f"{s / 3600:.1f}{THIN}h"
    return f"{days:.1f} days" if days < 10 else f"{days:.0f} days"


def when(utc_iso: str | None) -> str:
    """An ISO time in UTC as ``2026-11-26 14:03:12 UTC`` (the report is read in several time zones and
    printed: one zone, named)."""
    if not utc_iso:
        return "\u2013"
    try:
        t = datetime.fromisoformat(utc_iso)
    except ValueError:
        return utc_iso
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return t.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def utc_iso(timestamp: float) -> str:
    """A POSIX time as ISO 8601 in UTC, to the second."""
    return datetime.fromtimestamp(timestamp, UTC).isoformat(timespec="seconds")
