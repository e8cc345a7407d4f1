"""The station's door to the results database (:mod:`cell.results`). Each run records itself when its process
ends (``cell inspect`` does); a run the database could not take keeps a pending marker in its folder and a
``results_not_recorded`` line in its journal, and its files hold everything. The station offers those runs to
the database again every half minute (:meth:`ResultsSync.sync`), journals each one recorded later (its own
journal and the run's), and reads the runs list and SPC through the same store."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

from cell.config import load_cell_config
from cell.errors import CellError
from cell.runs import RunFolder
from cell.station.journal import StationJournal
from cell.station.settings import StationSettings


class ResultsSync:
    """The results store of the station's cell, and the runs still waiting for it."""

    def __init__(self, settings: StationSettings, journal: StationJournal) -> None:
        self.settings = settings
        self.journal = journal
        self.last_error: str | None = None
        self._store: Any = None
        self._lock = threading.Lock()

    def store(self) -> Any:
        """The :class:`cell.results.ResultsStore` the station's cell records into (opened once; it connects
        when first used)."""
        if self._store is None:
            from cell.results import open_results

            self._store = open_results(load_cell_config(self.settings.cell), self.settings.runs)
        return self._store

    def pending(self) -> list[Path]:
        """The run folders whose results wait for the database (their pending marker)."""
        from cell.results.folder import pending_folders

        return pending_folders(self.settings.runs, self.store().where)

    def waiting(self, run_dir: Path) -> str | None:
        """Why ``run_dir``'s results are not in the database yet, or None when they are (no marker)."""
        from cell.results.folder import PENDING_NAME

        try:
            marker = json.loads((run_dir / PENDING_NAME).read_text())
        except FileNotFoundError:
            return None
        except (OSError, json.JSONDecodeError):
            return "unknown"
        return str(marker.get("reason") or "unknown")

    def sync(self) -> int:
        """Record the waiting runs; journal each one that is in now. How many; 0 and :attr:`last_error` set
        when the database still cannot take them."""
        with self._lock:
            before = set(self.pending())
            if not before:
                return 0
            try:
                self.store().sync()
            except CellError as exc:  # still away: the runs keep waiting, nothing is lost
                self.last_error = str(exc)
                return 0
            self.last_error = None
            recorded = sorted(before - set(self.pending()))
            for run_dir in recorded:
                self.journal.log("results_recorded_later", run=run_dir.name)
                RunFolder(run_dir).log("results_recorded", database=self.store().where, later=True)
            return len(recorded)
