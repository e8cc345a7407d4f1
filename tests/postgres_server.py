"""A real PostgreSQL server for tests, from Debian's ``postgresql`` package: ``initdb`` into a temporary
folder, ``pg_ctl start`` listening on a unix socket in that folder only (no TCP port, so parallel test runs
and other servers on the machine never collide), trust authentication, fsync off (a test server).

initdb and postgres refuse to run as root: as root they run as the ``postgres`` system user (runuser), the
folder handed to it. Missing binaries skip the tests, unless CELL_REQUIRE_POSTGRES=1 (CI): then they fail.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

import pytest

BIN_GLOB = "/usr/lib/postgresql/*/bin"
REQUIRED = os.environ.get("CELL_REQUIRE_POSTGRES") == "1"


def postgres_bin() -> Path | None:
    """The newest installed PostgreSQL's bin folder (with initdb and pg_ctl), or None."""
    found = [Path(p) for p in sorted(Path("/").glob(BIN_GLOB.lstrip("/")), key=_version)]
    found = [p for p in found if (p / "initdb").is_file() and (p / "pg_ctl").is_file()]
    return found[-1] if found else None


def _version(path: Path) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in path.parent.name.split("."))
    except ValueError:
        return (0,)


def require_postgres() -> Path:
    """The bin folder, or skip (fail under CELL_REQUIRE_POSTGRES=1) naming what is missing."""
    bin_dir = postgres_bin()
    if bin_dir is None:
        message = f"PostgreSQL server binaries not found ({BIN_GLOB}/initdb): apt-get install postgresql"
        if REQUIRED:
            pytest.fail(message + " (CELL_REQUIRE_POSTGRES=1)")
        pytest.skip(message)
    if os.geteuid() == 0 and shutil.which("runuser") is None:
        pytest.fail("running as root needs runuser to start PostgreSQL as the postgres user")
    return bin_dir


class PostgresServer:
    """One server in its own folder: :meth:`start`, :meth:`stop` (also to simulate a lost database),
    :meth:`url` of a database, :meth:`create_database`, :meth:`destroy`."""

    def __init__(self, bin_dir: Path) -> None:
        self.bin = bin_dir
        self.folder = Path(tempfile.mkdtemp(prefix="cell-pg-"))
        self.data = self.folder / "data"
        self.log = self.folder / "server.log"
        self.as_user = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
        if self.as_user:
            shutil.chown(self.folder, "postgres", "postgres")
        self._run("initdb", "-D", str(self.data), "-U", "cell", "--auth=trust", "-E", "UTF8", "--no-sync")

    def _run(self, tool: str, *args: str) -> None:
        done = subprocess.run(
            [*self.as_user, str(self.bin / tool), *args], capture_output=True, text=True, timeout=120
        )
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{tool} failed ({done.returncode}): {done.stderr.strip()}\n{log}")

    def start(self) -> None:
        options = (
            f"-k {self.folder} -c listen_addresses='' -c fsync=off -c synchronous_commit=off "
            "-c full_page_writes=off -c max_connections=60 -c shared_buffers=16MB"
        )
        self._run(
            "pg_ctl", "-D", str(self.data), "-l", str(self.log), "-o", options, "-w", "-t", "60", "start"
        )

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "stop")

    def url(self, database: str = "postgres") -> str:
        """A SQLAlchemy/psycopg URL of ``database`` over the server's unix socket."""
        return f"postgresql://cell@/{database}?host={self.folder}"

    def create_database(self) -> str:
        """A new, empty database; its URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(host=str(self.folder), user="cell", dbname="postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def destroy(self) -> None:
        try:
            self.stop()
        except RuntimeError:
            pass
        shutil.rmtree(self.folder, ignore_errors=True)
