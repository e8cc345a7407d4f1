"""The results database: every inspection run's summary, per-region statistics, serial and operator, for
``cell history``, SPC and the station. SQLite in the runs root by default; a plant's PostgreSQL when the
cell config sets ``results_db: postgresql://...`` (docs/results-db.md).

    store = open_results(cfg, runs_root)
    store.record_run(run_dir)              # idempotent; the folder is the truth
    store.runs(part="box", verdict="fail") # newest first
    store.spc("box"), store.spc_csv("box")
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from cell.results.errors import ResultsDamaged, ResultsError, ResultsUnavailable
from cell.results.spc import Capability, Spc, SpcSeries, TrendPoint
from cell.results.store import SQLITE_NAME, ResultsStore, RunRow, VerificationRow

if TYPE_CHECKING:
    from cell.config import CellConfig

__all__ = [
    "Capability",
    "ResultsDamaged",
    "ResultsError",
    "ResultsStore",
    "ResultsUnavailable",
    "RunRow",
    "Spc",
    "SpcSeries",
    "TrendPoint",
    "VerificationRow",
    "open_results",
    "results_url",
]


def results_url(cfg: CellConfig | None, runs_root: Path) -> str:
    """The database a cell records into: its config's ``results_db``, else ``<runs_root>/results.sqlite``."""
    if cfg is not None and cfg.results_db:
        return cfg.results_db
    return f"sqlite:///{Path(runs_root).resolve() / SQLITE_NAME}"


def open_results(cfg: CellConfig | None, runs_root: Path) -> ResultsStore:
    """The results store of a cell (``cfg`` None: the runs root's SQLite file). Cheap: nothing connects
    before the first call that needs the database."""
    return ResultsStore(results_url(cfg, runs_root), runs_root, cfg.name if cfg is not None else "")
