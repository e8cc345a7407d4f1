"""The station's ASGI app: routes, sign-in and token pages, error pages, and the background loop that reaps
finished runs and retries the results the database could not take."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from urllib.parse import quote

from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.middleware.sessions import SessionMiddleware
from starlette.requests import Request
from starlette.responses import RedirectResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from cell.station import pages_results, pages_run, pages_tech
from cell.station.auth import NotAllowed, SignInNeeded, TokenGate, sign_in, sign_out, signed_in
from cell.station.core import HERE, Station, flash, station_of
from cell.station.settings import StationSettings, session_secret

REAP_S = 0.5  # how often finished children are looked for


async def home(request: Request) -> Response:
    return RedirectResponse("/start" if signed_in(request) else "/signin", status_code=303)


async def signin_page(request: Request) -> Response:
    station = station_of(request)
    context = {
        "user": None,
        "name": request.query_params.get("name", ""),
        "next": request.query_params.get("next", "/start"),
    }
    return station.templates.TemplateResponse(request, "signin.html", context)


async def token_page(request: Request) -> Response:
    station = station_of(request)
    if request.method == "POST":
        given = str((await request.form()).get("token", ""))
        if TokenGate.check(request, given, station.settings.token() or ""):
            station.journal.log("token_accepted", client=request.client.host if request.client else "?")
            return RedirectResponse("/signin", status_code=303)
        station.journal.log("token_refused", client=request.client.host if request.client else "?")
        flash(request, "Wrong station token.")
        return RedirectResponse("/token", status_code=303)
    return station.templates.TemplateResponse(request, "token.html", {"user": None})


async def _sign_in_needed(request: Request, exc: Exception) -> Response:
    return RedirectResponse(f"/signin?next={quote(request.url.path)}", status_code=303)


async def _not_allowed(request: Request, exc: Exception) -> Response:
    station = station_of(request)
    context = {"user": signed_in(request), "title": "Not allowed", "text": str(exc)}
    return station.templates.TemplateResponse(request, "message.html", context, status_code=403)


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, HTTPException)
    station = station_of(request)
    context = {"user": signed_in(request), "title": f"Error {exc.status_code}", "text": exc.detail}
    return station.templates.TemplateResponse(request, "message.html", context, status_code=exc.status_code)


def create_app(settings: StationSettings) -> Starlette:
    """The station app for ``settings`` (checked by the caller: :func:`.settings.check_settings`)."""
    station = Station(settings)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        station.journal.log(
            "station_started", host=settings.host, port=settings.port, runs=str(settings.runs)
        )
        task = asyncio.create_task(_background(station))
        try:
            yield
        finally:
            task.cancel()
            station.journal.log("station_stopped")

    middleware = [
        Middleware(
            SessionMiddleware,
            secret_key=session_secret(settings),
            session_cookie="cell_station",
            same_site="strict",
            https_only=settings.tls_cert is not None,
            max_age=12 * 3600,  # a shift
        )
    ]
    token = settings.token()
    if token:
        middleware.append(Middleware(TokenGate, token=token))
    routes = [
        Route("/", home),
        Route("/signin", signin_page),
        Route("/signin", sign_in, methods=["POST"]),
        Route("/signout", sign_out, methods=["POST"]),
        Route("/token", token_page, methods=["GET", "POST"]),
        Route("/start", pages_run.start_page),
        Route("/start", pages_run.start_run, methods=["POST"]),
        Route("/live", pages_run.current_run),
        Route("/run/{name}", pages_run.live_page),
        Route("/run/{name}/events", pages_run.events),
        Route("/run/{name}/verdict", pages_run.verdict_page),
        Route("/run/{name}/views/{view:int}/thumbnail.png", pages_run.thumbnail),
        Route("/run/{name}/views/{view:int}/photo.jpg", pages_run.photo),
        Route("/run/{name}/results/{path:path}", pages_run.result_file),
        Route("/run/{name}/{action}", pages_run.run_action, methods=["POST"]),
        Route("/runs", pages_results.runs_page),
        Route("/spc", pages_results.spc_index),
        Route("/spc/{recipe}", pages_results.spc_page),
        Route("/spc/{recipe}/{table}.csv", pages_results.spc_csv),
        Route("/calibrate", pages_tech.calibrate_page),
        Route("/calibrate", pages_tech.calibrate_start, methods=["POST"]),
        Route("/recipes", pages_tech.recipes_page),
        Route("/recipes/{key}", pages_tech.recipe_edit),
        Route("/recipes/{key}", pages_tech.recipe_save, methods=["POST"]),
        Mount("/static", StaticFiles(directory=str(HERE / "static")), name="static"),
    ]
    app = Starlette(
        routes=routes,
        middleware=middleware,
        lifespan=lifespan,
        exception_handlers={
            SignInNeeded: _sign_in_needed,
            NotAllowed: _not_allowed,
            HTTPException: _http_error,
        },
    )
    app.state.station = station
    return app


async def _background(station: Station) -> None:
    """Reap finished runs (recording their results) and offer unsynced results again, until cancelled."""
    since_retry = 0.0
    while True:
        try:
            await asyncio.to_thread(station.supervisor.poll)
            since_retry += REAP_S
            if since_retry >= station.settings.sync_every_s and station.supervisor.current() is None:
                since_retry = 0.0
                await asyncio.to_thread(station.results.sync)
        except Exception as exc:  # the loop must outlive one bad pass; the journal says what went wrong
            station.journal.log("background_error", error=repr(exc))
        await asyncio.sleep(REAP_S)
