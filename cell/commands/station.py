"""``cell station serve`` (the operator's web application) and ``cell station users add|list`` (who may sign
in), around :mod:`cell.station`."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from cell.defaults import DEFAULT_CELL, RUNS_ROOT

station_app = typer.Typer(
    help="The operator's web application on the cell PC, and its users.", no_args_is_help=True
)
users_app = typer.Typer(help="Who may sign in at the station: names, roles, PINs.", no_args_is_help=True)
RECIPES = Path(__file__).resolve().parents[2] / "recipes"
UsersOpt = typer.Option(None, "--users", help="users file (default: RUNS/.station/users.yaml)")
RunsOpt = typer.Option(RUNS_ROOT, "--runs", help="runs root: one folder per run, and .station/")


def _users_file(users: Path | None, runs: Path) -> Path:
    return users if users is not None else runs / ".station" / "users.yaml"


@station_app.command("serve")
def serve_cmd(
    cell: Path = typer.Option(DEFAULT_CELL, "--cell", help="cell config every inspection runs on"),
    recipes: Path = typer.Option(RECIPES, "--recipes", help="folder of recipes offered on the start page"),
    runs: Path = RunsOpt,
    users: Path = UsersOpt,
    host: str = typer.Option(
        "127.0.0.1", "--host", help="address to listen on; beyond 127.0.0.1 needs the three below"
    ),
    port: int = typer.Option(8400, "--port"),
    token_file: Path = typer.Option(
        None, "--token-file", help="file holding the access token (16+ characters)"
    ),
    tls_cert: Path = typer.Option(None, "--tls-cert", help="TLS certificate (PEM)"),
    tls_key: Path = typer.Option(None, "--tls-key", help="TLS private key (PEM)"),
    sync_every: float = typer.Option(
        30.0, "--sync-every", help="seconds between offering the results database the runs it missed"
    ),
) -> None:
    """Serve the station (start, live, verdict, runs, SPC pages) until Ctrl-C; runs it started go on."""
    scheme = "https" if tls_cert else "http"
    typer.echo(f"cell station on {scheme}://{host}:{port}/ (runs in {runs.resolve()}); Ctrl-C stops it")
    from cell.station.server import serve
    from cell.station.settings import StationSettings

    settings = StationSettings(
        cell=cell.resolve(),
        recipes=recipes.resolve(),
        runs=runs.resolve(),
        users=_users_file(users, runs).resolve(),
        sync_every_s=sync_every,
        host=host,
        port=port,
        token_file=token_file,
        tls_cert=tls_cert,
        tls_key=tls_key,
    )
    serve(settings)


@users_app.command("add")
def users_add_cmd(
    name: str = typer.Argument(..., help="the name the user signs in with"),
    role: str = typer.Option("operator", "--role", help="operator or technician"),
    runs: Path = RunsOpt,
    users: Path = UsersOpt,
    pin_stdin: bool = typer.Option(False, "--pin-stdin", help="read the PIN from the first line of stdin"),
) -> None:
    """Add a user (or replace one of the same name) with a PIN of 4-12 digits, stored scrypt-hashed."""
    from cell.errors import ConfigError
    from cell.station.users import Role, add_user

    if role not in ("operator", "technician"):
        raise ConfigError(f"unknown role '{role}': operator or technician", field="--role")
    if pin_stdin:
        pin = sys.stdin.readline().strip()
    else:
        pin = typer.prompt("PIN (4-12 digits)", hide_input=True, confirmation_prompt=True)
    path = _users_file(users, runs)
    replaced = add_user(path, name, Role(role), pin)
    typer.echo(f"{'replaced' if replaced else 'added'} {role} {name} in {path}")


@users_app.command("list")
def users_list_cmd(runs: Path = RunsOpt, users: Path = UsersOpt) -> None:
    """List the users and their roles (never their PINs)."""
    from cell.station.users import load_users

    for user in load_users(_users_file(users, runs)).users:
        typer.echo(f"{user.name}\t{user.role.value}")


def register(app: typer.Typer) -> None:
    station_app.add_typer(users_app, name="users")
    app.add_typer(station_app, name="station")
