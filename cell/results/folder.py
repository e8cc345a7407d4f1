"""What the results database stores about one inspection run, read from its folder alone (so that any
run can be recorded again, later or elsewhere): the manifest with the run's identity, the journal (start,
end, status), the copied recipe and cell config, and results/report.json (verdict, figures, regions)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.errors import ConfigError
from cell.run_record import sha256_file
from cell.runs import RunFolder

PENDING_NAME = "results-pending.json"  # in a run folder: its results are not in the database yet


@dataclass(frozen=True)
class RunRecord:
    """One run's row (column -> value of the ``runs`` table) and its per-region rows."""

    run: dict[str, Any]
    regions: list[dict[str, Any]] = field(default_factory=list)


def is_inspection_folder(path: Path) -> bool:
    return (path / "inputs" / "manifest.json").is_file() and (path / "journal.jsonl").is_file()


def _json(path: Path) -> dict[str, Any] | None:
    """A JSON file's object, or None when it is missing or torn (a report being written)."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _yaml(path: Path) -> dict[str, Any]:
    import yaml  # here: listing the database (`cell history`) reads no folder's YAML

    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _time(epoch: float) -> datetime:
    return datetime.fromtimestamp(epoch, UTC)


def _status(run: RunFolder, journal: list[dict[str, Any]]) -> tuple[str, datetime | None]:
    """(status, finished): the state of the run's last ``exit`` if nothing happened after it; else
    ``running`` while a live process holds the folder's lock, ``interrupted`` when none does (killed)."""
    status, finished = None, None
    for entry in journal:
        if entry.get("event") == "exit":
            status, finished = str(entry.get("state")), _time(float(entry["t"]))
        elif entry.get("event") in ("state", "resume", "run_created"):
            status, finished = None, None
    if status is not None:
        return status, finished
    holder = run.lock_holder()
    return ("running" if holder is not None and run.holder_is_live(holder) else "interrupted"), None


def _figure(doc: dict[str, Any], *keys: str) -> float | None:
    value: Any = doc
    for key in keys:
        value = value.get(key) if isinstance(value, dict) else None
    return None if value is None else float(value)


def read_run(run_dir: Path) -> RunRecord:
    """The record of the inspection run in ``run_dir``; ConfigError if it is not one."""
    run_dir = Path(run_dir).resolve()
    if not is_inspection_folder(run_dir):
        raise ConfigError(
            "not an inspection run folder (no inputs/manifest.json or journal)", path=str(run_dir)
        )
    run = RunFolder(run_dir)
    inputs = run_dir / "inputs"
    manifest = _json(inputs / "manifest.json") or {}
    journal = run.journal()
    created = next((e for e in journal if e.get("event") == "run_created"), {})
    recipe_file = inputs / str(manifest.get("recipe", "recipe.yaml"))
    recipe_doc = _yaml(recipe_file)
    sources = manifest.get("sources") or {}
    cad = Path(str(sources.get("cad") or manifest.get("cad") or "part"))
    part = str(created.get("part") or recipe_doc.get("name") or cad.stem)
    identity = manifest.get("identity") or {}
    report = _json(run.results_dir / "report.json") or {}
    status, finished = _status(run, journal)
    tolerance = report.get("tolerance") or {}
    row = {
        "cell": str(_yaml(inputs / str(manifest.get("cell", "cell.yaml"))).get("name") or ""),
        "folder": str(run_dir),
        "recipe": Path(str(sources.get("recipe") or part)).stem,
        "recipe_sha256": sha256_file(recipe_file),
        "part": part,
        "serial": identity.get("serial"),
        "operator": identity.get("operator"),
        "production_order": identity.get("order"),
        "started": run.started(),  # the report's start too (cell.run_record)
        "finished": finished,
        "status": status,
        "verdict": report.get("verdict"),
        "n_points": report.get("n_points"),
        "coverage": _figure(report, "coverage"),
        "dev_min": _figure(report, "deviation", "min_mm"),
        "dev_max": _figure(report, "deviation", "max_mm"),
        "dev_mean": _figure(report, "deviation", "mean_mm"),
        "dev_std": _figure(report, "deviation", "std_mm"),
        "tol_lower": _figure(tolerance, "lower_mm"),
        "tol_upper": _figure(tolerance, "upper_mm"),
    }
    regions = [
        {
            "name": str(r["name"]),
            "kind": r.get("kind"),
            "tol_lower": _figure(r, "tolerance", "lower_mm"),
            "tol_upper": _figure(r, "tolerance", "upper_mm"),
            "n_points": r.get("n_points"),
            "n_out": r.get("n_out_of_tolerance"),
            "mean": _figure(r, "mean_mm"),
            "min": _figure(r, "min_mm"),
            "max": _figure(r, "max_mm"),
            "coverage": _figure(r, "coverage"),
            "verdict": r.get("verdict"),
        }
        for r in report.get("region_verdicts") or []
        if isinstance(r, dict) and r.get("name")
    ]
    return RunRecord(row, regions)


def inspection_folders(root: Path) -> list[Path]:
    """Every inspection run folder directly under ``root`` (hidden, partial folders are not runs yet)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if not p.name.startswith(".") and is_inspection_folder(p))


def mark_pending(run_dir: Path, reason: str, database: str) -> None:
    """Note in the folder that its results are not in ``database`` yet, and why."""
    from cell.runs import write_json_atomic

    write_json_atomic(
        Path(run_dir) / PENDING_NAME,
        {"since": datetime.now(UTC).isoformat(timespec="seconds"), "database": database, "reason": reason},
    )


def pending_folders(root: Path, database: str) -> list[Path]:
    """The folders under ``root`` whose results wait to be recorded in ``database`` (a folder waiting for
    another database, a cell's PostgreSQL when this is the runs root's SQLite file, is left to that one)."""
    root = Path(root)
    if not root.is_dir():
        return []
    out = []
    for marker in sorted(root.glob(f"*/{PENDING_NAME}")):
        if marker.parent.name.startswith("."):
            continue
        if (_json(marker) or {}).get("database", database) == database:
            out.append(marker.parent)
    return out


def read_verification(path: Path) -> dict[str, Any] | None:
    """The ``verifications`` row of a finished verification folder (its ``verification.json``: a ``cell
    verify check`` is kind ``check``, a full test ``acceptance``), or None when the folder holds none."""
    doc = _json(Path(path) / "verification.json")
    if doc is None or not doc.get("cell") or "figures_mm" not in doc:
        return None
    try:
        time = datetime.fromisoformat(str(doc["created_utc"]))
    except (KeyError, ValueError):
        time = datetime.fromtimestamp((Path(path) / "verification.json").stat().st_mtime, UTC)
    figures = doc["figures_mm"] or {}
    return {
        "cell": str(doc["cell"]),
        "folder": str(Path(path).resolve()),
        "kind": "check" if doc.get("interim") else "acceptance",
        "time": time if time.tzinfo else time.replace(tzinfo=UTC),
        "verdict": str(doc.get("verdict") or "incomplete"),
        **{k.lower(): figures.get(k) for k in ("PF", "PS", "SD", "F")},
    }


def verification_folders(root: Path) -> list[Path]:
    """Every folder directly under ``root`` holding a verification result (verification.json)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(
        p for p in root.iterdir() if not p.name.startswith(".") and (p / "verification.json").is_file()
    )
