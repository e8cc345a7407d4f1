"""A run's progress as the operator reads it, from its folder alone (journal and views): the state in words,
view k of n, the time left including the post-processing, the last measured view. The station never asks the
process running the inspection; what is on disk is the truth (a restarted station reads the same).

The time left comes from the latest finished runs of the same part: how long they took from the point this run
has reached (their k-th capture) to their end, so the feedback loop's extra views, the registration and the
report are in it. Before any run of the part has finished, it is the views left at this run's pace plus half
the scanning time for the post-processing, and the page says it is a first estimate.
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cell.runs import RunFolder, folder_safe

TERMINAL = ("done", "paused", "faulted", "aborted")
DEFAULT_VIEW_S = 3.0  # before the second capture of a run and without history: a view takes about this

_WORDS = {
    "idle": "Starting",
    "resuming": "Resuming from the last completed view",
    "connecting": "Connecting to the robot, projector and camera",
    "homing": "Moving the robot to its home position",
    "planning": "Planning the views",
    "scanning_moving": "Moving to view {view}",
    "scanning_capturing": "Measuring view {view}",
    "scanning_decoding": "Decoding the last views",
    "evaluating": "Checking what the views cover",
    "replanning": "Planning extra views for what is missing",
    "registering": "Aligning the views to the part",
    "reporting": "Comparing with the CAD model",
    "rendering": "Verdict ready; writing the report's pictures and page",
    "done": "Finished",
    "paused": "Paused",
    "faulted": "Stopped by a fault",
    "aborted": "Aborted",
}


@dataclass
class Progress:
    """What the live page shows; ``view`` counts from 1, ``left_s`` is None when it cannot be estimated."""

    name: str
    state: str | None = None
    words: str = "Starting: checking the recipe and copying the inputs"
    message: str = ""
    view: int | None = None
    views_total: int = 0
    views_done: int = 0
    last_view: int | None = None  # the index of the newest complete view folder (its thumbnail)
    elapsed_s: float = 0.0
    left_s: float | None = None
    left_note: str = ""
    serial: str | None = None
    operator: str | None = None
    part: str | None = None
    verdict: str | None = None
    kind: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Timeline:
    """An uninterrupted finished run's clock (s since the epoch): its first state, its captures, its end."""

    start: float
    captures: tuple[float, ...]
    done: float


def _timeline(entries: list[dict[str, Any]]) -> Timeline | None:
    """The timeline of a finished run that ran in one go (one process, no pause), else None."""
    states = [e for e in entries if e.get("event") == "state"]
    exits = [e for e in entries if e.get("event") == "exit"]
    if not states or states[-1].get("state") != "done" or len(exits) != 1:
        return None
    captures = tuple(float(e["t"]) for e in entries if e.get("event") == "capture")
    return Timeline(float(states[0]["t"]), captures, float(states[-1]["t"]))


def history(runs_root: Path, part: str, exclude: Path | None = None, last: int = 5) -> list[Timeline]:
    """The timelines of the latest ``last`` finished, uninterrupted runs of ``part`` under ``runs_root``."""
    found: list[tuple[str, Timeline]] = []
    for folder in runs_root.glob(f"{folder_safe(part)}-*"):
        if folder == exclude or not (folder / "journal.jsonl").is_file():
            continue
        try:
            if json.loads((folder / "checkpoint.json").read_text()).get("phase") != "done":
                continue
        except (OSError, json.JSONDecodeError):
            continue
        timeline = _timeline(RunFolder(folder).journal())
        if timeline is not None:
            found.append((folder.name, timeline))
    return [t for _, t in sorted(found)[-last:]]


def read_progress(run_dir: Path, past: list[Timeline] | None = None, now: float | None = None) -> Progress:
    """The progress of the run in ``run_dir`` (which may not exist yet: the run is starting). ``past`` is
    :func:`history` of the run's part (looked up by the caller, once), for the time left."""
    p = Progress(run_dir.name)
    if not (run_dir / "journal.jsonl").is_file():
        return p
    now = time.time() if now is None else now
    run = RunFolder(run_dir)
    entries = run.journal()
    created = next((e for e in entries if e.get("event") == "run_created"), {})
    p.part, p.serial, p.operator = created.get("part"), created.get("serial"), created.get("operator")
    p.kind = run.kind
    states = [e for e in entries if e.get("event") == "state"]
    if states:
        p.state, p.message = states[-1]["state"], states[-1].get("message", "")
        p.elapsed_s = now - float(entries[0]["t"])
    checkpoint = run.load_checkpoint() or {}
    p.views_total = len(checkpoint.get("views", []))
    done_views = run.completed_views()
    p.views_done = len(done_views)
    p.last_view = done_views[-1] if done_views else None
    capture_t = [float(e["t"]) for e in entries if e.get("event") == "capture"]
    captured = [int(e["view"]) for e in entries if e.get("event") == "capture"]
    if p.state == "scanning_capturing" and captured:
        p.view = captured[-1] + 1
    elif p.state == "scanning_moving":  # to the next view neither captured nor complete
        p.view = min(len(set(captured) | set(done_views)) + 1, max(p.views_total, 1))
    p.words = _WORDS.get(p.state or "idle", p.state or "").format(view=p.view or "")
    asked = [e for e in entries if e.get("event") == "operator" and e.get("action") == "pause"]
    if p.state == "paused" and asked and float(asked[-1]["t"]) <= float(states[-1]["t"]):
        p.words = f"Paused by {asked[-1].get('by')}"
        # the station asks as Ctrl-C does (SIGINT), so the controller says Ctrl-C: the words say who asked
        p.message = p.message.removeprefix("pause requested: Ctrl-C").removeprefix("; ")
    if checkpoint.get("phase") in ("rendering", "done"):  # the verdict is published before the report's page
        p.verdict = (checkpoint.get("summary") or {}).get("verdict")
    if p.state == "done":
        p.elapsed_s = float(states[-1]["t"]) - float(entries[0]["t"])
    if p.state not in TERMINAL:
        started = [float(e["t"]) for e in states if e.get("state") in ("connecting", "resuming")]
        p.left_s, p.left_note = _time_left(p, capture_t, started[-1] if started else now, past or [], now)
    return p


def _time_left(
    p: Progress, captures: list[float], started: float, past: list[Timeline], now: float
) -> tuple[float | None, str]:
    """Seconds to the end of the run, post-processing included, and a note on how sure that is.

    With finished runs of the part: the median time those runs took from the same point (their k-th capture
    when this run has made k, their first state before any) to their end, less the time since this run
    passed it; the feedback loop's extra views and the registration and report are in it. Without: the views
    left at this run's pace plus half the scanning time for the rest (a guess, said so)."""
    k = len(captures)
    since = now - (captures[-1] if captures else started)
    if past:
        if k == 0:
            ahead = [t.done - t.start for t in past]
        else:
            ahead = [t.done - t.captures[k - 1] for t in past if len(t.captures) >= k]
            if not ahead:  # more views than the earlier runs made: what followed their last capture
                ahead = [t.done - t.captures[-1] for t in past if t.captures]
        if ahead:
            left = statistics.median(ahead) - since
            return (left, "") if left > 0 else (None, "finishing: taking longer than the last runs")
    if not p.views_total:
        return None, "known once the views are planned"
    intervals = [b - a for a, b in zip(captures, captures[1:])]
    per_view = statistics.median(intervals) if intervals else DEFAULT_VIEW_S
    to_measure = max(p.views_total - p.views_done, 0)
    left = to_measure * per_view + 0.5 * per_view * p.views_total - (since if not to_measure else 0.0)
    note = "a first estimate: no run of this part has finished here yet"
    return (left, note) if left > 0 else (None, "finishing")
