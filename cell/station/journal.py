"""The station's journal: what happened at the station that no run folder holds (sign-ins, refused starts,
wrong PINs, results the database could not take), one JSON object per line, appended and fsynced like a run's
journal. It lives in ``<runs root>/.station/journal.jsonl``."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any


class StationJournal:
    """Append-only JSON lines in ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)

    def log(self, event: str, **fields: Any) -> None:
        """Append one entry (time, event, fields) and fsync it."""
        line = json.dumps({"t": time.time(), "event": event, **fields}, default=str) + "\n"
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def entries(self) -> list[dict[str, Any]]:
        """Every complete entry (a torn last line is skipped)."""
        if not self.path.exists():
            return []
        out = []
        for line in self.path.read_text(encoding="utf-8").splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out
