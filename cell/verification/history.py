"""The verification history: every interim check's figures (and any acceptance test stored with them) in the
runs root's SQLite index (its own table beside the inspections' ``runs`` table), their trend and the drift
warning.

Drift: a check warns when a figure has used more than ``warn_fraction`` of its maximum permissible error, or
when the straight line through the last checks of a figure (at least three) reaches the MPE within
``horizon`` further checks, so a slow drift is flagged before it fails.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from cell.runs import INDEX_NAME
from cell.verification.procedure import AcceptanceResult

FIGURES = ("PF", "PS", "SD", "F")


@dataclass(frozen=True)
class Entry:
    """One stored verification: when, what kind, its folder, worst figures (mm) and verdict."""

    time: str
    kind: str
    folder: str
    cell: str
    figures_mm: dict[str, float | None]
    verdict: str


class VerificationHistory:
    """The ``verification`` table of ``<runs root>/index.sqlite``."""

    def __init__(self, root: Path) -> None:
        self.path = Path(root) / INDEX_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute(
                "CREATE TABLE IF NOT EXISTS verification (folder TEXT PRIMARY KEY, time TEXT, kind TEXT, "
                "cell TEXT, pf REAL, ps REAL, sd REAL, f REAL, verdict TEXT)"
            )

    def _connect(self) -> sqlite3.Connection:
        return sqlite3.connect(self.path, timeout=10)

    def add(self, folder: Path, kind: str, result: AcceptanceResult, time: str | None = None) -> None:
        """Store one result (``time``: ISO 8601 UTC, default now)."""
        f = result.figures_mm
        with self._connect() as db:
            db.execute(
                "INSERT OR REPLACE INTO verification VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    str(Path(folder).resolve()),
                    time or datetime.now(UTC).isoformat(timespec="seconds"),
                    kind,
                    result.cell,
                    f["PF"],
                    f["PS"],
                    f["SD"],
                    f["F"],
                    result.verdict,
                ),
            )

    def entries(self, cell: str | None = None) -> list[Entry]:
        """Every stored verification of ``cell`` (all cells when None), oldest first."""
        query = "SELECT folder, time, kind, cell, pf, ps, sd, f, verdict FROM verification"
        args: tuple = ()
        if cell is not None:
            query, args = query + " WHERE cell=?", (cell,)
        with self._connect() as db:
            rows = db.execute(query + " ORDER BY time", args).fetchall()
        return [
            Entry(t, kind, folder, c, dict(zip(FIGURES, (pf, ps, sd, f), strict=True)), verdict)
            for folder, t, kind, c, pf, ps, sd, f, verdict in rows
        ]


def drift_warnings(
    entries: list[Entry],
    mpe_mm: dict[str, float],
    *,
    warn_fraction: float = 0.7,
    horizon: int = 5,
    window: int = 6,
) -> list[str]:
    """Warnings for the newest entry of ``entries`` (oldest first): a figure past ``warn_fraction`` of its
    MPE, or one whose linear trend over the last ``window`` entries reaches the MPE within ``horizon``
    further checks. Empty when there is nothing to warn about."""
    out: list[str] = []
    if not entries:
        return out
    for k in FIGURES:
        series = [f for e in entries[-window:] if (f := e.figures_mm[k]) is not None]
        if not series:
            continue
        now, mpe = abs(series[-1]), mpe_mm[k]
        if now > mpe:
            out.append(f"{k} {now * 1000:.1f} um exceeds its MPE {mpe * 1000:.1f} um")
        elif now > warn_fraction * mpe:
            out.append(f"{k} {now * 1000:.1f} um uses {now / mpe:.0%} of its MPE {mpe * 1000:.1f} um")
        elif len(series) >= 3:
            x = np.arange(len(series), dtype=float)
            slope, intercept = np.polyfit(x, np.abs(series), 1)
            if slope > 0:
                ahead = (mpe - (intercept + slope * x[-1])) / slope
                if ahead <= horizon:
                    out.append(
                        f"{k} drifts: its size grows {slope * 1000:.1f} um per check and reaches the MPE "
                        f"{mpe * 1000:.1f} um in about {max(ahead, 0):.0f} more checks"
                    )
    return out


def inspection_block(root: Path, cell: str, block: bool = True) -> str | None:
    """Why ``cell`` may not inspect now: its newest verification in ``root``'s history failed (the figures
    over their MPE, when and where), or None (no verification yet, the newest passed, or ``block`` is off).
    A cell never checked is not blocked: the check is the technician's shift routine, not a precondition."""
    if not block or not (Path(root) / INDEX_NAME).is_file():
        return None
    entries = VerificationHistory(root).entries(cell)
    if not entries or entries[-1].verdict != "fail":
        return None
    last = entries[-1]
    shown = ", ".join(f"{k} {abs(v) * 1000:.1f} um" for k, v in last.figures_mm.items() if v is not None)
    return (
        f"cell '{cell}' failed its last verification ({last.kind}, {last.time}: {shown}; "
        f"folder {last.folder}): inspections are blocked until a `cell verify check` passes again "
        "(recalibrate first: `cell calibrate all`), or the cell config sets verification.block_inspections: "
        "false"
    )
