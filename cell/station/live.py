"""What the live page shows of one run, as one JSON-able snapshot: its progress read from the folder, whether
its process is running here, which of Pause, Resume and Abort the page offers (the server checks again when
one is pressed; the controller has the last word), and whether the run is over (the page then shows the
verdict, as soon as it is published)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cell.runs import LOCK_NAME, RAW_IMAGES, RunFolder
from cell.station.progress import TERMINAL, Progress, Timeline, read_progress
from cell.station.supervisor import Supervisor


def duration_text(seconds: float | None) -> str:
    """``45 s``, ``2 min 05 s``, ``1 h 03 min``; empty for None."""
    if seconds is None:
        return ""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def snapshot(supervisor: Supervisor, runs: Path, name: str, past: list[Timeline] | None) -> dict[str, Any]:
    """The live page's view of run ``name`` (a folder under ``runs``, or a run still starting)."""
    rec = supervisor.record(name)
    running = rec is not None and rec.exit_code is None and supervisor.current() == rec
    progress = read_progress(runs / name, past)
    failed = None
    if not (runs / name / "journal.jsonl").is_file() and rec is not None and not running:
        failed = rec.error or f"the process ended with exit code {rec.exit_code} before the run began"
        progress = Progress(name, words="Could not start", message=failed)
    inspection = progress.kind in (None, "inspection") and (rec is None or rec.kind != "calibrate")
    state = progress.state
    elsewhere = None  # a process this station did not start works on the run (a terminal's `cell inspect`)
    if not running and (runs / name / LOCK_NAME).is_file():
        folder = RunFolder(runs / name)
        holder = folder.lock_holder()
        if holder is not None and folder.holder_is_live(holder):
            elsewhere = f"run by another process (PID {holder.get('pid')}, {holder.get('command')})"
    free = not running and elsewhere is None
    actions = {
        "pause": running and state is not None and state not in TERMINAL,
        "resume": free and inspection and state is not None and state not in ("done", "aborted"),
        "abort": inspection
        and state not in ("done", "rendering", "aborted", None)  # a published verdict stands
        and failed is None
        and elsewhere is None,
    }
    # over for the operator once the verdict is out: the report's page follows while the verdict page shows
    final = failed is not None or (free and state in ("done", "aborted")) or state == "rendering"
    if elsewhere:
        progress.message = f"{elsewhere}; {progress.message}" if progress.message else elsewhere
    elif not running and state is not None and state not in TERMINAL:
        progress.words = "Stopped (the process ended without pausing: it was killed or lost)"
    return {
        **progress.to_json(),
        "running": running,
        "failed": failed,
        "actions": actions,
        "final": final,
        "elapsed_text": duration_text(progress.elapsed_s) if state else "",
        "left_text": duration_text(progress.left_s),
        "user": rec.user if rec else progress.operator,
        "thumbnail": (
            f"/run/{name}/views/{progress.last_view}/thumbnail.png"
            if progress.last_view is not None
            else None
        ),
        # the view's photo while its raw images are kept (the cell's retention; a passed run's go at its end)
        "photo": (
            f"/run/{name}/views/{progress.last_view}/photo.jpg"
            if progress.last_view is not None
            and (RunFolder(runs / name).view_dir(progress.last_view) / RAW_IMAGES / "capture.yaml").is_file()
            else None
        ),
    }
