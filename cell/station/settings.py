"""What one station serves (its cell, recipes, runs root, users file) and where it listens.

The station binds to 127.0.0.1 by default: only the cell PC itself reaches it. Binding to any other address
(``--host 0.0.0.0``) is refused unless a token file and a TLS certificate and key are given: a browser on the
network then has to present the token once (it is kept in the session) and talks over HTTPS only.
"""

from __future__ import annotations

import ipaddress
import os
import secrets
from pathlib import Path

from pydantic import Field

from cell.config import load_cell_config
from cell.errors import ConfigError
from cell.schema import Strict

LOOPBACK = "127.0.0.1"


class StationSettings(Strict):
    """Everything ``cell station serve`` needs; paths are as given (relative to the working folder)."""

    cell: Path = Field(description="cell config YAML every inspection runs on")
    recipes: Path = Field(description="folder of recipe YAML files offered on the start page")
    runs: Path = Field(description="runs root: one folder per run, and .station/ (journal, logs, secret)")
    users: Path = Field(description="users file (cell station users add)")
    sync_every_s: float = Field(
        30.0, gt=0, description="how often runs the database missed are offered again"
    )
    host: str = LOOPBACK
    port: int = Field(8400, ge=1, le=65535)
    token_file: Path | None = Field(None, description="file holding the access token for a wider binding")
    tls_cert: Path | None = None
    tls_key: Path | None = None

    @property
    def state_dir(self) -> Path:
        """The station's own files under the runs root: journal, child logs, session secret."""
        return self.runs / ".station"

    @property
    def wide(self) -> bool:
        """True when the station listens beyond this machine."""
        try:
            return not ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return self.host != "localhost"

    def token(self) -> str | None:
        """The access token for a wide binding (None on loopback)."""
        if not self.wide or self.token_file is None:
            return None
        return self.token_file.read_text().strip()


def check_settings(settings: StationSettings) -> None:
    """ConfigError naming the option when the station cannot serve: a missing cell, recipes folder or users
    file, or a binding beyond loopback without a token (16+ characters) and a TLS certificate and key."""
    for option, path, is_dir in (
        ("--cell", settings.cell, False),
        ("--recipes", settings.recipes, True),
        ("--users", settings.users, False),
    ):
        if not (path.is_dir() if is_dir else path.is_file()):
            what = "folder" if is_dir else "file"
            hint = "; add the first user with `cell station users add NAME --role technician`" * (
                option == "--users"
            )
            raise ConfigError(f"{what} not found{hint}", path=str(path), field=option)
    load_cell_config(settings.cell)  # a cell config that cannot run stops the station here, named
    if not settings.wide:
        return
    missing = [
        option
        for option, value in (
            ("--token-file", settings.token_file),
            ("--tls-cert", settings.tls_cert),
            ("--tls-key", settings.tls_key),
        )
        if value is None or not value.is_file()
    ]
    if missing:
        raise ConfigError(
            f"binding to {settings.host} lets other machines reach the station; it needs "
            f"{', '.join(missing)} (a file holding a token of 16+ characters, a TLS certificate and key); "
            "or bind to 127.0.0.1 (docs/station.md, 'Binding beyond this PC')",
            field="--host",
        )
    token = settings.token() or ""
    if len(token) < 16:
        raise ConfigError("the token must be at least 16 characters", path=str(settings.token_file))


def session_secret(settings: StationSettings) -> str:
    """The key that signs session cookies: made once per runs root, readable by its owner only; a restarted
    station keeps its operators signed in."""
    path = settings.state_dir / "session.key"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another station made it meanwhile
            return path.read_text().strip()
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))
    return path.read_text().strip()
