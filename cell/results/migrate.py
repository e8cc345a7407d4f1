"""Create or upgrade the results database's schema by running its Alembic migrations (``migrations/``)
programmatically, for SQLite and PostgreSQL alike. Concurrent openers are serialised: PostgreSQL by an
advisory lock, SQLite by its write lock (the store's transactions begin IMMEDIATE)."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import Engine, text

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
_PG_LOCK = 0x63656C6C  # pg_advisory_xact_lock key: "cell"


def head() -> str:
    """The newest schema revision the code knows."""
    from alembic.script import ScriptDirectory

    rev = ScriptDirectory(str(MIGRATIONS)).get_current_head()
    assert rev is not None
    return rev


def current(engine: Engine) -> str | None:
    """The database's schema revision (None: no schema yet)."""
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def upgrade(engine: Engine) -> bool:
    """Bring the schema to :func:`head` in one transaction; True if anything was migrated."""
    from alembic import command
    from alembic.config import Config

    from cell.results.errors import ResultsUnavailable

    now, known = current(engine), head()
    if now == known:
        return False
    if now is not None and now not in _revisions():
        raise ResultsUnavailable(
            f"the results database's schema (revision {now}) is newer than this software knows (up to "
            f"{known}): update the cell software; nothing was changed in the database"
        )
    # write=True: on SQLite the store's "begin" listener takes the write lock at once (BEGIN IMMEDIATE), so
    # two first openers queue instead of both reading "no schema" and one failing to write
    with engine.connect() as conn, conn.execution_options(write=True).begin():
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _PG_LOCK})
        config = Config()
        config.set_main_option("script_location", str(MIGRATIONS))
        config.attributes["connection"] = conn
        command.upgrade(config, "head")
    return True


def _revisions() -> set[str]:
    from alembic.script import ScriptDirectory

    return {r.revision for r in ScriptDirectory(str(MIGRATIONS)).walk_revisions()}
