"""How long a finished inspection run keeps its raw view images, and the pruning that applies it
(``cell prune``; docs/storage.md).

A run's raw images are its views' pattern stacks (``views/NNN/raw/``, :mod:`cell.view_files`): what a view can
be decoded again from, or audited with, and by far the largest thing a run could keep (about 13 MB a view at
1024x768, 8 bits, 38 frames: camera noise leaves little to compress). Everything else stays for ever: results,
inputs, journal, checkpoint and the decoded views, so a pruned run's report still opens and ``cell report``
still rebuilds it (it reads the decoded views, never the raw images).

Only finished runs are pruned (checkpoint phase ``done``): an unfinished run can still be resumed. A run in
use (its lock held by a live process) is skipped. A run's age is counted from the time its journal records it
reaching ``done``, not from file times: those change when a runs root is copied or restored, or a report is
rebuilt, and would restart or cut short the period.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from pydantic import Field, ValidationError

from cell.errors import ConfigError
from cell.run_data import Phase
from cell.runs import RAW_IMAGES, RunFolder
from cell.schema import Strict

DAY_S = 86400.0
PRUNING = ".raw.pruning"  # a raw folder being deleted (renamed first: a killed prune leaves no half stack)


class RetentionConfig(Strict):
    """How long a finished inspection run keeps its raw view images (``views/NNN/raw/``: each view's pattern
    stack, lossless), by verdict: days after the run finished, 0 not past its end, null for ever. Results,
    inputs, journal, checkpoint and the decoded views are always kept. ``cell prune`` applies it; a run
    applies it to itself when it finishes, so 0 days removes them then. Both 0: raw images are not written."""

    raw_images_passed_days: float | None = Field(
        0.0,
        ge=0,
        le=36500,
        description="a passed part's raw images: not kept by default (13 MB a view of the 1024x768 8-bit "
        "camera; its results and decoded views stay)",
    )
    raw_images_failed_days: float | None = Field(
        30.0,
        ge=0,
        le=36500,
        description="raw images of a failed or incomplete run: kept a month by default, for the review "
        "of the part and to decode it again (cell scan --from views/NNN/raw)",
    )

    @property
    def writes_raw_images(self) -> bool:
        """Whether a run writes its raw images at all (the verdict is not known while it captures)."""
        return self.raw_images_passed_days != 0 or self.raw_images_failed_days != 0

    def keep_days(self, verdict: str | None) -> float | None:
        """The days a run of ``verdict`` keeps its raw images (None: for ever)."""
        return self.raw_images_passed_days if verdict == "pass" else self.raw_images_failed_days


@dataclass
class RunPrune:
    """One run's raw images and what the policy does with them."""

    run: Path
    verdict: str | None
    finished_t: float | None  # UNIX time of the journal's ``done`` (None: not finished)
    raw_dirs: list[Path]
    raw_bytes: int
    action: str  # "delete", "keep", "skip"
    reason: str
    freed_bytes: int = 0


@dataclass
class PruneReport:
    """What a prune found, did (or, in a dry run, would do) in a runs root."""

    root: Path
    dry_run: bool
    runs: list[RunPrune] = field(default_factory=list)

    @property
    def freed_bytes(self) -> int:
        return sum(r.freed_bytes for r in self.runs)

    @property
    def to_free_bytes(self) -> int:
        return sum(r.raw_bytes for r in self.runs if r.action == "delete")


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def raw_dirs(run: RunFolder) -> list[Path]:
    """The run's raw image folders (``views/NNN/raw``), with any a killed prune left half deleted."""
    views = run.path / "views"
    if not views.is_dir():
        return []
    return sorted(p for d in views.iterdir() for p in (d / RAW_IMAGES, d / PRUNING) if p.is_dir())


def finished_time(run: RunFolder) -> float:
    """When the run reached ``done`` (UNIX time): its journal's entry, else (a journal that lost it) the time
    the checkpoint was last written, which a finished run writes when it reaches ``done``."""
    for entry in run.journal():
        if entry.get("event") == "state" and entry.get("state") == Phase.DONE.value:
            return float(entry["t"])
    return run.checkpoint_path.stat().st_mtime


def run_policy(run: RunFolder) -> RetentionConfig:
    """The retention of the cell config the run was made with (its ``inputs/``; defaults if it has none)."""
    manifest = json.loads((run.path / "inputs" / "manifest.json").read_text())
    path = run.path / "inputs" / manifest["cell"]
    data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    try:
        return RetentionConfig.model_validate(data.get("retention") or {})
    except ValidationError as exc:
        raise ConfigError(f"invalid retention section: {exc.errors()[0]['msg']}", path=str(path)) from exc


def assess(run: RunFolder, policy: RetentionConfig, now: float) -> RunPrune:
    """What ``policy`` does with ``run``'s raw images at time ``now`` (reads only)."""
    checkpoint = run.load_checkpoint() or {}
    verdict = (checkpoint.get("summary") or {}).get("verdict")
    dirs = raw_dirs(run)
    entry = RunPrune(run.path, verdict, None, dirs, sum(_size(d) for d in dirs), "skip", "")
    if not dirs:
        entry.reason = "no raw images"
        return entry
    if checkpoint.get("phase") != Phase.DONE.value:
        entry.reason = f"not finished (phase {checkpoint.get('phase')}): it can still be resumed"
        return entry
    holder = run.lock_holder()
    if holder is not None and run.holder_is_live(holder) and holder.get("pid") != os.getpid():
        entry.reason = f"in use by PID {holder.get('pid')} on {holder.get('host')} ({holder.get('command')})"
        return entry
    entry.finished_t = finished_time(run)
    days = policy.keep_days(verdict)
    which = "passed" if verdict == "pass" else f"{verdict or 'unjudged'}"
    if days is None:
        entry.action, entry.reason = "keep", f"{which}: raw images kept for ever"
        return entry
    age_days = (now - entry.finished_t) / DAY_S
    entry.action = "keep" if age_days < days else "delete"
    entry.reason = f"{which}, finished {age_days:.1f} days ago: raw images kept {days:g} days"
    return entry


def delete_raw(run: RunFolder, entry: RunPrune, policy: RetentionConfig, *, locked: bool = False) -> None:
    """Delete ``entry``'s raw folders under the run's lock (taken here unless ``locked``: the caller holds
    it) and journal it. Each folder is renamed aside first: a prune killed midway leaves a ``.raw.pruning``
    folder that the next prune removes, never half a stack under the name a reader looks for."""
    if not locked:
        run.acquire_lock("cell prune")
    try:
        if (run.load_checkpoint() or {}).get("phase") != Phase.DONE.value:
            entry.action, entry.reason = "skip", "no longer finished"
            return
        freed = 0
        for d in entry.raw_dirs:
            if not d.exists():
                continue
            size = _size(d)
            doomed = d if d.name == PRUNING else d.rename(d.with_name(PRUNING))
            shutil.rmtree(doomed)
            freed += size
        entry.freed_bytes = freed
        # reopened under the lock: a torn last line (a killed process's) is cut, so this entry starts a line
        RunFolder.open(run.path).log(
            "prune",
            removed=[str(d.relative_to(run.path)) for d in entry.raw_dirs],
            freed_bytes=freed,
            reason=entry.reason,
            policy=policy.model_dump(),
        )
    finally:
        if not locked:
            run.release_lock()


def inspection_runs(root: Path) -> Iterator[RunFolder]:
    """The inspection run folders directly under ``root`` (hidden folders of runs being created skipped)."""
    if not root.is_dir():
        raise ConfigError("runs root not found", path=str(root), field="--runs")
    for path in sorted(root.iterdir()):
        if path.name.startswith(".") or not path.is_dir():
            continue
        # not RunFolder.open: it cuts a torn last journal line, in a running run the line being written
        run = RunFolder(path)
        if run.journal_path.is_file() and run.kind == "inspection":
            yield run


def prune(
    root: Path, policy: RetentionConfig | None = None, *, dry_run: bool = False, now: float | None = None
) -> PruneReport:
    """Apply the retention to every finished inspection run under ``root``: ``policy`` (a cell config's) for
    all, or each run's own (None). A dry run reads only."""
    now = time.time() if now is None else now
    report = PruneReport(root, dry_run)
    for run in inspection_runs(root):
        try:
            pol = policy if policy is not None else run_policy(run)
        except ConfigError as exc:  # that run's own policy is unreadable: leave it, say why
            report.runs.append(RunPrune(run.path, None, None, raw_dirs(run), 0, "skip", str(exc)))
            continue
        entry = assess(run, pol, now)
        if entry.action == "delete" and not dry_run:
            try:
                delete_raw(run, entry, pol)
            except ConfigError as exc:  # taken by another process meanwhile
                entry.action, entry.reason = "skip", str(exc)
        report.runs.append(entry)
    return report


def apply_at_finish(run: RunFolder, policy: RetentionConfig) -> RunPrune | None:
    """At the end of a finished run, by the process that holds its lock: remove its raw images now if its
    verdict keeps them 0 days (the entry), else leave them for ``cell prune`` (None)."""
    entry = assess(run, policy, time.time())
    if entry.action == "delete" and policy.keep_days(entry.verdict) == 0:
        delete_raw(run, entry, policy, locked=True)
        return entry
    return None
