"""The technician's pages: calibration routines (run as children like inspections, followed on the live page)
and recipe edits (the new text is validated as a recipe before it replaces the file). Operators are refused
with a message saying who may."""

from __future__ import annotations

import asyncio

from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import RedirectResponse, Response

from cell.errors import CellError
from cell.station.auth import require
from cell.station.core import flash, said, station_of
from cell.station.recipes import list_recipes, save_recipe
from cell.station.supervisor import ROUTINES
from cell.station.users import Role

ROUTINE_HELP = {
    "sensor": "per-pixel sensor model (the stage steps the reference board)",
    "intrinsics": "camera lens (ChArUco board views)",
    "projector": "projector lens and pose",
    "gamma": "projector response",
    "handeye": "robot kinematics and the sensor on the flange",
    "latency": "trigger and exposure timing",
    "validate": "check the calibration on the artefact",
    "all": "every routine in a row (minutes)",
}


async def calibrate_page(request: Request) -> Response:
    user = require(request, Role.TECHNICIAN)
    station = station_of(request)
    return station.templates.TemplateResponse(
        request,
        "calibrate.html",
        {"user": user, "routines": [(r, ROUTINE_HELP[r]) for r in ROUTINES], "cell": station.settings.cell},
    )


async def calibrate_start(request: Request) -> Response:
    user = require(request, Role.TECHNICIAN)
    station = station_of(request)
    routine = str((await request.form()).get("routine", ""))
    try:
        rec = station.supervisor.start_calibration(routine, user.name)
    except CellError as exc:
        station.journal.log("start_refused", user=user.name, routine=routine[:40], why=said(exc))
        flash(request, f"Not started: {said(exc)}")
        return RedirectResponse("/calibrate", status_code=303)
    return RedirectResponse(f"/run/{rec.run}", status_code=303)


async def recipes_page(request: Request) -> Response:
    user = require(request, Role.TECHNICIAN)
    station = station_of(request)
    recipes = await asyncio.to_thread(list_recipes, station.settings.recipes)
    return station.templates.TemplateResponse(request, "recipes.html", {"user": user, "recipes": recipes})


async def recipe_edit(request: Request) -> Response:
    user = require(request, Role.TECHNICIAN)
    station = station_of(request)
    key = request.path_params["key"]
    entry = next((r for r in list_recipes(station.settings.recipes) if r.key == key), None)
    if entry is None:
        raise HTTPException(404, f"unknown recipe {key!r}")
    text = entry.path.read_text(encoding="utf-8")
    return station.templates.TemplateResponse(
        request, "recipe_edit.html", {"user": user, "entry": entry, "text": text, "error": None}
    )


async def recipe_save(request: Request) -> Response:
    user = require(request, Role.TECHNICIAN)
    station = station_of(request)
    key = request.path_params["key"]
    text = str((await request.form()).get("text", ""))
    try:
        await asyncio.to_thread(save_recipe, station.settings.recipes, key, text)
    except CellError as exc:
        station.journal.log("recipe_refused", user=user.name, recipe=key, why=said(exc))
        entry = next((r for r in list_recipes(station.settings.recipes) if r.key == key), None)
        if entry is None:
            raise HTTPException(404, f"unknown recipe {key!r}") from None
        context = {"user": user, "entry": entry, "text": text, "error": f"Not saved: {said(exc)}"}
        return station.templates.TemplateResponse(request, "recipe_edit.html", context, status_code=400)
    station.journal.log("recipe_saved", user=user.name, recipe=key)
    flash(request, f"Recipe {key} saved.", "info")
    return RedirectResponse("/recipes", status_code=303)
