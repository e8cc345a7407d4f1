"""Runs and SPC pages, read from the results database (:mod:`cell.results`): the runs filtered by part,
serial, verdict, operator and date; per recipe the trends of the mean and the extreme deviation and the
per-region Cp/Cpk, with CSV export. A database that cannot answer is said on the page, in one line."""

from __future__ import annotations

import asyncio
from datetime import datetime, timedelta
from typing import Any
from urllib.parse import urlencode

from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import Response

from cell.errors import CellError
from cell.station.auth import require
from cell.station.core import station_of
from cell.station.recipes import list_recipes
from cell.station.spc_chart import trend_svg

FILTERS = ("part", "serial", "verdict", "operator", "since", "until")
PAGE = 100  # runs on one page


def _day(text: str, field: str) -> datetime | None:
    """A date from the filter form (YYYY-MM-DD, local midnight), or None when empty."""
    if not text:
        return None
    try:
        return datetime.strptime(text, "%Y-%m-%d").astimezone()
    except ValueError:
        raise CellError(f"{field} '{text}' is not a date (YYYY-MM-DD)") from None


async def runs_page(request: Request) -> Response:
    user = require(request)
    station = station_of(request)
    q = {k: request.query_params.get(k, "").strip() for k in FILTERS}
    given = request.query_params.get("page", "0")
    page = int(given) if given.isdigit() else 0  # newest first, PAGE runs a page
    rows: list[Any] = []
    choices: dict[str, list[str]] = {"part": [], "verdict": [], "operator": []}
    error = None
    store = station.results.store()
    try:
        since, until = _day(q["since"], "from"), _day(q["until"], "to")
        filters = {k: q[k] or None for k in ("part", "serial", "verdict", "operator")}
        rows = await asyncio.to_thread(
            store.runs,
            **filters,
            since=since,
            until=until + timedelta(days=1) if until else None,  # the whole last day
            limit=PAGE + 1,  # one more: is there an older page?
            offset=page * PAGE,
        )
        for column in choices:
            choices[column] = await asyncio.to_thread(store.distinct, column)
    except CellError as exc:
        error = str(exc)
        station.journal.log("results_unreadable", page="runs", error=error)
    here = {str(p.resolve()): p.name for p in station.settings.runs.iterdir()}
    context = {
        "user": user,
        "q": q,
        "rows": rows[:PAGE],
        "error": error,
        "choices": choices,
        "here": here,
        "page": page,
        "older": len(rows) > PAGE,
        "query": urlencode({k: v for k, v in q.items() if v}),
    }
    return station.templates.TemplateResponse(request, "runs.html", context)


async def spc_index(request: Request) -> Response:
    user = require(request)
    station = station_of(request)
    recipes = await asyncio.to_thread(list_recipes, station.settings.recipes)
    context = {"user": user, "recipes": recipes}
    return station.templates.TemplateResponse(request, "spc_index.html", context)


async def spc_page(request: Request) -> Response:
    user = require(request)
    station = station_of(request)
    recipe = request.path_params["recipe"]
    spc, charts, error = None, [], None
    try:
        spc = await asyncio.to_thread(station.results.store().spc, recipe)
        for s in spc.series:
            title = "whole part" if not s.name else f"region {s.name}"
            charts.append((title, await asyncio.to_thread(trend_svg, s, title) if s.trend else None))
    except CellError as exc:
        error = str(exc)
        station.journal.log("results_unreadable", page="spc", error=error)
    context = {"user": user, "recipe": recipe, "spc": spc, "charts": charts, "error": error}
    return station.templates.TemplateResponse(request, "spc.html", context)


async def spc_csv(request: Request) -> Response:
    require(request)
    station = station_of(request)
    recipe, table = request.path_params["recipe"], request.path_params["table"]
    if table not in ("trend", "capability"):
        raise HTTPException(404, f"no SPC table {table!r}: trend or capability")
    try:
        text = await asyncio.to_thread(station.results.store().spc_csv, recipe, table)
    except CellError as exc:
        raise HTTPException(503, str(exc)) from None
    name = f"spc-{recipe}-{table}.csv"
    return Response(
        text, media_type="text/csv", headers={"Content-Disposition": f'attachment; filename="{name}"'}
    )
