"""Signing in (a name and a PIN, checked against the users file's scrypt hashes), the roles a page needs, and
the token gate of a station bound beyond 127.0.0.1. The session is a signed cookie (Starlette's
SessionMiddleware: itsdangerous, HttpOnly, SameSite=strict, Secure under TLS)."""

from __future__ import annotations

import hmac
from typing import Any
from urllib.parse import quote

from starlette.requests import Request
from starlette.responses import RedirectResponse, Response
from starlette.types import ASGIApp, Receive, Scope, Send

from cell.station.core import flash, station_of
from cell.station.users import Role, User, authenticate


class SignInNeeded(Exception):
    """The page needs a signed-in user; the handler sends the browser to the sign-in page."""


class NotAllowed(Exception):
    """The signed-in user's role may not do this; the message says who may."""


def signed_in(request: Request) -> User | None:
    """The signed-in user, if still in the users file (a removed user is signed out)."""
    name = request.session.get("user")
    if not name:
        return None
    return station_of(request).users().find(name)


def require(request: Request, role: Role | None = None) -> User:
    """The signed-in user, who must hold ``role`` when given (a technician may do what an operator may)."""
    user = signed_in(request)
    if user is None:
        raise SignInNeeded()
    if role is Role.TECHNICIAN and user.role is not Role.TECHNICIAN:
        station_of(request).journal.log("refused", user=user.name, path=request.url.path, why="role")
        raise NotAllowed(
            f"{user.name} is signed in as an operator: only a technician may run calibration routines or "
            "edit recipes. Ask a technician to sign in."
        )
    return user


async def sign_in(request: Request) -> Response:
    """POST /signin: name and PIN; wrong ones are told as one message (which of the two is not said)."""
    station = station_of(request)
    form = await request.form()
    name, pin = str(form.get("name", "")).strip(), str(form.get("pin", ""))
    user = authenticate(station.users(), name, pin)
    if user is None:
        station.journal.log("sign_in_failed", name=name[:64], client=_client(request))
        flash(request, "Wrong name or PIN. Try again, or ask a technician to check your user.")
        return RedirectResponse(f"/signin?name={quote(name[:64])}", status_code=303)
    request.session["user"] = user.name
    station.journal.log("signed_in", user=user.name, role=user.role.value, client=_client(request))
    return RedirectResponse(_safe_next(str(form.get("next", ""))), status_code=303)


async def sign_out(request: Request) -> Response:
    """POST /signout."""
    name = request.session.pop("user", None)
    if name:
        station_of(request).journal.log("signed_out", user=name)
    return RedirectResponse("/signin", status_code=303)


def _safe_next(target: str) -> str:
    """A local path to go to after signing in (never another site)."""
    return target if target.startswith("/") and not target.startswith("//") else "/start"


def _client(request: Request) -> str:
    return request.client.host if request.client else "?"


class TokenGate:
    """ASGI middleware for a station bound beyond loopback: a browser presents the station's token once (the
    /token page; kept in its session) or as ``Authorization: Bearer TOKEN``; everything else is sent there."""

    OPEN = ("/token", "/static/")

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"].startswith(self.OPEN) or self._passes(scope):
            await self.app(scope, receive, send)
            return
        await RedirectResponse("/token", status_code=303)(scope, receive, send)

    def _passes(self, scope: Scope) -> bool:
        session: dict[str, Any] = scope.get("session", {})
        if session.get("token_ok"):
            return True
        headers = dict(scope.get("headers", []))
        given = headers.get(b"authorization", b"").decode(errors="replace").removeprefix("Bearer ").strip()
        return bool(given) and hmac.compare_digest(given, self.token)

    @staticmethod
    def check(request: Request, given: str, token: str) -> bool:
        """The /token form: remember a right token in the session."""
        ok = hmac.compare_digest(given.strip(), token)
        if ok:
            request.session["token_ok"] = True
        return ok
