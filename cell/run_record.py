"""What an inspection's report says about its run: who and what (serial, operator, order), when it started,
and which inputs it ran with (recipe and cell config, by file name and SHA-256 of the copies the run read).

Read from the run folder itself (``inputs/manifest.json``, the copies in ``inputs/``, the start the journal
records: :meth:`cell.runs.RunFolder.started`, which the results database states too), so a rebuilt report
says the same as the first one. The identity is the one
:func:`cell.inspection_run.run_identity` reads; it is read here from the manifest directly because the job
(:mod:`cell.inspection`) must not import the run level above it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from cell.runs import RunFolder


def sha256_file(path: Path) -> str | None:
    """Hex SHA-256 of a file's bytes, or None when it is missing."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def run_record(run: RunFolder, cell_name: str | None = None) -> dict[str, Any]:
    """``{folder, started_utc, identity{serial, operator, order}, recipe{file, sha256}, cell{name, file,
    sha256}}`` of an inspection run (an older run without a field gives nulls)."""
    inputs = run.path / "inputs"
    try:
        manifest = json.loads((inputs / "manifest.json").read_text())
    except (OSError, ValueError):
        manifest = {}
    sources = manifest.get("sources") or {}
    recipe = manifest.get("recipe")
    cell = manifest.get("cell_as_given") or manifest.get("cell")  # the user's file, not the run's rewrite
    identity = manifest.get("identity") or {}
    return {
        "folder": run.path.name,
        "started_utc": started.isoformat(timespec="seconds") if (started := run.started()) else None,
        "identity": {k: identity.get(k) for k in ("serial", "operator", "order")},
        "recipe": {
            "file": sources.get("recipe") or recipe,
            "sha256": sha256_file(inputs / recipe) if recipe else None,
        },
        "cell": {
            "name": cell_name,
            "file": sources.get("cell") or cell,
            "sha256": sha256_file(inputs / cell) if cell else None,
        },
    }
