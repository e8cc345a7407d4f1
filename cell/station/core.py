"""The station's shared state for the pages: its settings, journal, users file (reread when it changes),
supervisor, results store and templates. One per app (``request.app.state.station``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from starlette.requests import Request
from starlette.templating import Jinja2Templates

from cell.station.journal import StationJournal
from cell.station.results import ResultsSync
from cell.station.settings import StationSettings
from cell.station.supervisor import Supervisor
from cell.station.users import UsersFile, load_users

HERE = Path(__file__).resolve().parent


class Station:
    """Everything a page handler needs, built once when the app starts."""

    def __init__(self, settings: StationSettings) -> None:
        self.settings = settings
        self.journal = StationJournal(settings.state_dir / "journal.jsonl")
        self.results = ResultsSync(settings, self.journal)
        self.supervisor = Supervisor(settings, self.journal)
        self.templates = Jinja2Templates(directory=str(HERE / "templates"), context_processors=[_flash])
        self._users: tuple[float, UsersFile] | None = None

    def users(self) -> UsersFile:
        """The users file, reread when its modification time changes (a user added while serving)."""
        mtime = self.settings.users.stat().st_mtime
        if self._users is None or self._users[0] != mtime:
            self._users = (mtime, load_users(self.settings.users))
        return self._users[1]


def said(exc: Exception) -> str:
    """An error as the page says it: a ConfigError without its "field '--serial': " prefix (a page has no
    command-line options; the message names what is wrong)."""
    text = str(exc)
    field = getattr(exc, "field", None)
    return text.replace(f"field '{field}': ", "", 1) if field else text


def flash(request: Request, text: str, kind: str = "error") -> None:
    """A message shown once on the next page (kind: error, info)."""
    request.session.setdefault("flash", []).append({"kind": kind, "text": text})


def _flash(request: Request) -> dict[str, Any]:
    messages = request.session.pop("flash", []) if "session" in request.scope else []
    return {"messages": messages}


def station_of(request: Request) -> Station:
    """The station serving ``request``."""
    station: Station = request.app.state.station
    return station
