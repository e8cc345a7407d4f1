"""The station's door to the results database (:mod:`cell.results`): every run that reached a verdict is
recorded there when its process ends. When the database cannot take it (connection lost, server down), the
run is listed in ``<runs root>/.station/unsynced.json`` and the failure is journalled (the station's journal
and the run's); :meth:`ResultsSync.retry` records the listed runs once the database answers again. Nothing is
lost: the run folder holds everything the database gets."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

from cell.runs import RunFolder, write_json_atomic
from cell.station.journal import StationJournal
from cell.station.settings import StationSettings


class ResultsSync:
    """Records finished runs in the results database, keeping those it could not record for later."""

    def __init__(self, settings: StationSettings, journal: StationJournal) -> None:
        self.settings = settings
        self.journal = journal
        self.pending_path = settings.state_dir / "unsynced.json"
        self.last_error: str | None = None
        self._store: Any = None
        self._lock = threading.Lock()

    def store(self) -> Any:
        """The results store (opened once)."""
        if self._store is None:
            from cell.results import open_results

            self._store = open_results(self.settings.results_url, self.settings.runs)
        return self._store

    def pending(self) -> list[str]:
        """Names of the run folders not yet in the database."""
        try:
            return list(json.loads(self.pending_path.read_text()))
        except (OSError, json.JSONDecodeError):
            return []

    def _set_pending(self, names: list[str]) -> None:
        write_json_atomic(self.pending_path, sorted(set(names)))

    def record(self, run_dir: Path) -> bool:
        """Record one run; on failure keep it for :meth:`retry` and journal why. True when recorded."""
        with self._lock:
            try:
                self.store().record_run(run_dir)
            except Exception as exc:  # any database failure: the run waits in the list, nothing is lost
                self.last_error = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
                if run_dir.name in self.pending():
                    return False  # journalled when it first failed
                self._set_pending([*self.pending(), run_dir.name])
                message = (
                    f"results database unreachable ({self.last_error}); the run is kept in its folder and "
                    "will be recorded when the database answers again"
                )
                self.journal.log("results_unsynced", run=run_dir.name, error=self.last_error)
                RunFolder(run_dir).log("results", synced=False, message=message)
                return False
            self._set_pending([n for n in self.pending() if n != run_dir.name])
            self.last_error = None
            RunFolder(run_dir).log("results", synced=True)
            return True

    def retry(self) -> int:
        """Record the runs still waiting, stopping at the first failure; returns how many were recorded."""
        done = 0
        for name in self.pending():
            run_dir = self.settings.runs / name
            if not run_dir.is_dir():
                self._set_pending([n for n in self.pending() if n != name])
                continue
            if not self.record(run_dir):
                break
            self.journal.log("results_synced", run=name, later=True)
            done += 1
        return done
