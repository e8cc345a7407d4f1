"""Create or upgrade the results database's schema by running its Alembic migrations (``migrations/``)
programmatically, for SQLite and PostgreSQL alike. Concurrent openers are serialised: PostgreSQL by an
advisory lock, SQLite by its write lock (the store's transactions begin IMMEDIATE).

Every command that reads the database opens it through :func:`upgrade`, so an up-to-date schema is told
cheaply: its revision is read from Alembic's version table with SQLAlchemy Core and compared with
:data:`HEAD`; Alembic itself (0.2-0.3 s of CPU to import and to read the migration scripts) is loaded only
when the schema is missing or behind."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import Connection, Engine, inspect, text

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
HEAD = "0001"  # the newest revision in migrations/versions (tests/test_results_db.py checks it is Alembic's)
VERSION_TABLE = "alembic_version"  # Alembic's default, where it keeps the schema's revision
_PG_LOCK = 0x63656C6C  # pg_advisory_xact_lock key: "cell"


def current(engine: Engine) -> str | None:
    """The database's schema revision (None: no schema yet)."""
    with engine.connect() as conn:
        return _revision(conn)


def _revision(conn: Connection) -> str | None:
    """The revision in Alembic's version table, read as Alembic reads it (none: no table or no row)."""
    if not inspect(conn).has_table(VERSION_TABLE):
        return None
    rows = list(conn.execute(text(f"SELECT version_num FROM {VERSION_TABLE}")).scalars())
    if len(rows) > 1:  # branches, which this linear history never makes: Alembic's own reading says so
        from alembic.runtime.migration import MigrationContext

        return MigrationContext.configure(conn).get_current_revision()
    return rows[0] if rows else None


def upgrade(engine: Engine) -> bool:
    """Bring the schema to :func:`head` in one transaction; True if anything was migrated."""
    now = current(engine)
    if now == HEAD:
        return False
    return _migrate(engine, now)


def _migrate(engine: Engine, now: str | None) -> bool:
    from alembic import command
    from alembic.config import Config

    from cell.results.errors import ResultsUnavailable

    if now is not None and now not in _revisions():
        raise ResultsUnavailable(
            f"the results database's schema (revision {now}) is newer than this software knows (up to "
            f"{HEAD}): update the cell software; nothing was changed in the database"
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


def alembic_head() -> str:
    """The head revision as Alembic reads it from the migration scripts (for the test of :data:`HEAD`)."""
    from alembic.script import ScriptDirectory

    rev = ScriptDirectory(str(MIGRATIONS)).get_current_head()
    assert rev is not None
    return rev


def _revisions() -> set[str]:
    from alembic.script import ScriptDirectory

    return {r.revision for r in ScriptDirectory(str(MIGRATIONS)).walk_revisions()}
