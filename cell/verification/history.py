"""The verification history: every interim check's figures (and any acceptance test stored with them) in the
results database (``cell.results``: the runs root's results.sqlite, or the plant's PostgreSQL that the cell
config names, so a cell's history follows its name across runs roots), their trend and the drift warning.

Drift: a check warns when a figure has used more than ``warn_fraction`` of its maximum permissible error, or
when the straight line through the last checks of a figure (at least three) reaches the MPE within
``horizon`` further checks, so a slow drift is flagged before it fails.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cell.config import CellConfig
    from cell.verification.procedure import AcceptanceResult  # its figures import scipy (0.5-1 s)

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
    """The ``verifications`` table of the results database of ``cfg`` (None: ``<root>/results.sqlite``).
    Its methods raise ``cell.results.ResultsError`` when the database cannot be used; the verification's
    folder (verification.json) keeps the figures, and ``cell history --sync`` or ``--rebuild`` records
    them."""

    def __init__(self, root: Path, cfg: CellConfig | None = None) -> None:
        from cell.results import open_results

        self.store = open_results(cfg, root)

    def add(self, folder: Path, kind: str, result: AcceptanceResult, time: str | None = None) -> None:
        """Store one result (``time``: ISO 8601 UTC, default now)."""
        when = datetime.fromisoformat(time) if time else None
        self.store.record_verification(folder, kind, result.cell, result.figures_mm, result.verdict, when)

    def entries(self, cell: str | None = None) -> list[Entry]:
        """Every stored verification of ``cell`` (all cells when None), oldest first."""
        return [
            Entry(v.time.isoformat(timespec="seconds"), v.kind, v.folder, v.cell, v.figures_mm, v.verdict)
            for v in self.store.verifications(cell)
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
            import numpy as np  # here: `cell verify history` lists the checks without numpy (0.1-0.2 s)

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


def inspection_block(root: Path, cell: str, block: bool = True, cfg: CellConfig | None = None) -> str | None:
    """Why ``cell`` may not inspect now: its newest verification failed (the figures over their MPE, when
    and where), or None (no verification yet, the newest passed, or ``block`` is off). A cell never checked
    is not blocked: the check is the technician's shift routine, not a precondition.

    The verifications are read from the results database of ``cfg`` (None: ``root``'s results.sqlite); when
    it cannot be read (server down, file damaged), from the verification folders in ``root`` themselves,
    which is where this cell's checks were written: a lost database neither blocks nor unblocks a cell."""
    if not block:
        return None
    from cell.results import ResultsError

    try:
        entries = VerificationHistory(root, cfg).entries(cell)
    except ResultsError:
        entries = local_entries(root, cell)
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


def local_entries(root: Path, cell: str | None = None) -> list[Entry]:
    """The verifications of ``cell`` (all when None) read from the folders in ``root`` (their
    verification.json), oldest first: the history without the database."""
    from cell.results.folder import read_verification, verification_folders

    rows = [r for p in verification_folders(root) if (r := read_verification(p)) is not None]
    rows = sorted((r for r in rows if cell is None or r["cell"] == cell), key=lambda r: r["time"])
    return [
        Entry(
            r["time"].isoformat(timespec="seconds"),
            r["kind"],
            r["folder"],
            r["cell"],
            {k: r[k.lower()] for k in FIGURES},
            r["verdict"],
        )
        for r in rows
    ]
