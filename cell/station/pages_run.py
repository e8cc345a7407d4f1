"""The operator's pages around one run: start (scan or type the serial, pick the recipe), live (progress by
server-sent events; Pause, Resume, Abort), verdict (PASS / FAIL / INCOMPLETE with the reasons and the run's
report), and the files behind them (view thumbnails, the report)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from sse_starlette.sse import EventSourceResponse
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import FileResponse, RedirectResponse, Response

from cell.errors import CellError, ConfigError
from cell.station.auth import require
from cell.station.core import flash, said, station_of
from cell.station.live import snapshot
from cell.station.progress import Timeline, history, read_progress
from cell.station.recipes import find_recipe, list_recipes
from cell.station.thumbnail import legend_css, view_photo, view_thumbnail
from cell.station.verdict import read_verdict

POLL_S = 0.4  # how often a live page's stream looks at the run folder


def _run_name(request: Request) -> str:
    """The run named in the URL: a folder under the runs root, or a run this station started (starting)."""
    station = station_of(request)
    name = request.path_params["name"]
    known = (station.settings.runs / name / "journal.jsonl").is_file() or station.supervisor.record(name)
    if "/" in name or name.startswith(".") or not known:
        raise HTTPException(404, f"no run named {name!r} under {station.settings.runs}")
    return name


async def start_page(request: Request) -> Response:
    user = require(request)
    station = station_of(request)
    current = station.supervisor.current()
    recipes = await asyncio.to_thread(list_recipes, station.settings.recipes)
    chosen = request.query_params.get("recipe") or request.session.get("recipe")
    valid = [r for r in recipes if not r.problem]
    if chosen not in [r.key for r in valid]:
        chosen = valid[0].key if len(valid) == 1 else None
    return station.templates.TemplateResponse(
        request,
        "start.html",
        {
            "user": user,
            "recipes": recipes,
            "chosen": chosen,
            "serial": request.query_params.get("serial", ""),
            "current": current,
            "unsynced": [p.name for p in station.results.pending() if not current or p.name != current.run],
        },
    )


async def start_run(request: Request) -> Response:
    user = require(request)
    station = station_of(request)
    form = await request.form()
    serial, key = str(form.get("serial", "")), str(form.get("recipe", ""))
    try:
        station.supervisor.check_identity(serial, user.name)  # what was scanned first is checked first
        if not key:
            raise ConfigError("pick the recipe of the part first", field="recipe")
        entry = await asyncio.to_thread(find_recipe, station.settings.recipes, key)
        rec = station.supervisor.start_inspection(entry, serial, user.name)
    except CellError as exc:
        station.journal.log(
            "start_refused", user=user.name, serial=serial[:80], recipe=key[:80], why=said(exc)
        )
        flash(request, f"Not started: {said(exc)}")
        return RedirectResponse("/start?" + urlencode({"serial": serial[:80], "recipe": key[:80]}), 303)
    request.session["recipe"] = key
    return RedirectResponse(f"/run/{rec.run}", status_code=303)


async def current_run(request: Request) -> Response:
    require(request)
    rec = station_of(request).supervisor.current()
    return RedirectResponse(f"/run/{rec.run}" if rec else "/start", status_code=303)


async def live_page(request: Request) -> Response:
    user = require(request)
    name = _run_name(request)
    station = station_of(request)
    snap = snapshot(station.supervisor, station.settings.runs, name, None)
    if snap["final"] and not snap["failed"]:
        return RedirectResponse(f"/run/{name}/verdict", status_code=303)
    return station.templates.TemplateResponse(
        request, "live.html", {"user": user, "name": name, "snap": snap, "legend": legend_css()}
    )


async def events(request: Request) -> Response:
    """Server-sent events: the run's snapshot (live.snapshot) whenever it changes, until the run is over."""
    require(request)
    name = _run_name(request)
    station = station_of(request)

    async def stream() -> AsyncIterator[dict[str, Any]]:
        past: list[Timeline] | None = None
        last = None
        while True:
            snap = await asyncio.to_thread(snapshot, station.supervisor, station.settings.runs, name, past)
            if snap["part"] and past is None:  # the part's history, once: the time left needs it
                past = await asyncio.to_thread(
                    history, station.settings.runs, snap["part"], station.settings.runs / name
                )
                continue
            data = json.dumps(snap)
            if data != last:
                yield {"event": "progress", "data": data}
                last = data
            if snap["final"]:
                return
            await asyncio.sleep(POLL_S)

    return EventSourceResponse(stream(), ping=10)


async def run_action(request: Request) -> Response:
    """POST /run/{name}/pause|resume|abort: asks the supervisor; a refusal is shown on the live page."""
    user = require(request)
    name = _run_name(request)
    action = request.path_params["action"]
    station = station_of(request)
    try:
        if action == "pause":
            station.supervisor.pause(name, user.name)
            flash(request, "Pause requested: the robot stops safely, then the run pauses.", "info")
        elif action == "resume":
            station.supervisor.resume(name, user.name)
            flash(request, "Resuming from the last completed view.", "info")
        elif action == "abort":
            await asyncio.to_thread(station.supervisor.abort, name, user.name)
            flash(request, "The run was aborted. Its measured data stay in the run folder.", "info")
            return RedirectResponse(f"/run/{name}/verdict", status_code=303)
        else:
            raise HTTPException(404, f"no action {action!r}")
    except CellError as exc:
        station.journal.log(f"{action}_refused", user=user.name, run=name, why=said(exc))
        flash(request, f"{action.capitalize()} refused: {said(exc)}")
    return RedirectResponse(f"/run/{name}", status_code=303)


async def verdict_page(request: Request) -> Response:
    user = require(request)
    name = _run_name(request)
    station = station_of(request)
    run_dir = station.settings.runs / name
    progress = read_progress(run_dir)
    if progress.state not in ("done", "rendering", "aborted", "faulted"):
        return RedirectResponse(f"/run/{name}", status_code=303)
    verdict = await asyncio.to_thread(read_verdict, run_dir, _region_boxes(run_dir))
    report = run_dir / "results" / "report.html"
    rec = station.supervisor.record(name)
    output = None
    if progress.kind not in (None, "inspection") and rec is not None:  # a calibration: what it printed
        lines = Path(rec.log).read_text(errors="replace").splitlines() if Path(rec.log).is_file() else []
        output = "\n".join(lines[-80:])
    return station.templates.TemplateResponse(
        request,
        "verdict.html",
        {
            "user": user,
            "name": name,
            "progress": progress,
            "verdict": verdict,
            "report": f"/run/{name}/results/report.html" if report.is_file() else None,
            "unsynced": station.results.waiting(run_dir) if progress.kind == "inspection" else None,
            "output": output,
        },
    )


def _region_boxes(run_dir: Path) -> list[tuple[str, list[list[float]]]]:
    """The box regions of the run's own recipe copy (name, [lo, hi] in the part frame, mm)."""
    import yaml

    try:
        recipe = yaml.safe_load((run_dir / "inputs" / "recipe.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return []
    return [(r["name"], r["box_mm"]) for r in recipe.get("regions") or [] if r.get("box_mm")]


async def thumbnail(request: Request) -> Response:
    """The view's map of what each camera pixel measured (PNG, 320 px wide)."""
    return await _view_picture(request, view_thumbnail, "image/png", "picture")


async def photo(request: Request) -> Response:
    """The view's fully lit frame, downscaled (JPEG, 320 px wide); 404 once its raw images are gone."""
    return await _view_picture(request, view_photo, "image/jpeg", "photo (its raw images are not kept)")


async def _view_picture(
    request: Request, make: Callable[[Path], bytes], media_type: str, what: str
) -> Response:
    require(request)
    name = _run_name(request)
    view = request.path_params["view"]
    view_dir = station_of(request).settings.runs / name / "views" / f"{view:03d}"
    try:
        data = await asyncio.to_thread(make, view_dir)
    except FileNotFoundError:
        raise HTTPException(404, f"view {view} of {name} has no {what}") from None
    # private: behind the sign-in; an hour: a view's pictures do not change (its photo can only go)
    return Response(data, media_type=media_type, headers={"Cache-Control": "private, max-age=3600"})


async def result_file(request: Request) -> Response:
    """A file of the run's results/ folder (report.html and what it references); nothing outside it."""
    require(request)
    name = _run_name(request)
    results = (station_of(request).settings.runs / name / "results").resolve()
    path = (results / request.path_params["path"]).resolve()
    if not path.is_relative_to(results) or not path.is_file():
        raise HTTPException(404, "no such result file")
    return FileResponse(path)
