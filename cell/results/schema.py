"""The results database's tables (SQLAlchemy Core), the same on SQLite and PostgreSQL.

The tables are created and changed only by the Alembic migrations in ``cell/results/migrations`` (run on
open); this module describes them for the queries. Times are stored as naive UTC and read back aware, so
SQLite (no time zones) and PostgreSQL compare them the same way.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    Column,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    UniqueConstraint,
)
from sqlalchemy.types import TypeDecorator

metadata = MetaData()


class UTCDateTime(TypeDecorator[datetime]):
    """An aware datetime in, naive UTC stored, aware UTC out (SQLite keeps no zone, PostgreSQL would)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("results database times must be timezone-aware")
        return value.astimezone(UTC).replace(tzinfo=None)

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        return None if value is None else value.replace(tzinfo=UTC)


runs = Table(
    "runs",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("cell", String(200), nullable=False),  # the cell config's name
    Column("folder", Text, nullable=False),  # the run folder's absolute path on the cell's machine
    Column("recipe", String(200), nullable=False),  # the recipe file's stem
    Column("recipe_sha256", String(64)),
    Column("part", String(200), nullable=False),  # the recipe's name (or the CAD file's stem)
    Column("serial", String(64)),
    Column("operator", String(64)),
    Column("production_order", String(64)),
    Column("started", UTCDateTime, nullable=False),
    Column("finished", UTCDateTime),
    Column("status", String(32), nullable=False),  # running, done, paused, fault, aborted, interrupted
    Column("verdict", String(32)),
    Column("n_points", Integer),
    Column("coverage", Float),
    Column("dev_min", Float),  # mm, signed deviation: positive outside the material
    Column("dev_max", Float),
    Column("dev_mean", Float),
    Column("dev_std", Float),
    Column("tol_lower", Float),  # the recipe's band, mm
    Column("tol_upper", Float),
    Column("recorded", UTCDateTime, nullable=False),
    UniqueConstraint("cell", "folder", name="uq_runs_cell_folder"),
)

regions = Table(
    "run_regions",
    metadata,
    Column("run_id", Integer, ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True),
    Column("name", String(200), primary_key=True),
    Column("kind", String(16)),  # faces or box
    Column("tol_lower", Float),
    Column("tol_upper", Float),
    Column("n_points", Integer),
    Column("n_out", Integer),
    Column("mean", Float),
    Column("min", Float),
    Column("max", Float),
    Column("coverage", Float),
    Column("verdict", String(32)),
)

verifications = Table(
    "verifications",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("cell", String(200), nullable=False),
    Column("folder", Text, nullable=False),
    Column("kind", String(32), nullable=False),  # check (cell verify check) or acceptance
    Column("time", UTCDateTime, nullable=False),
    Column("pf", Float),  # VDI/VDE 2634 figures, mm
    Column("ps", Float),
    Column("sd", Float),
    Column("f", Float),
    Column("verdict", String(32), nullable=False),
    UniqueConstraint("cell", "folder", name="uq_verifications_cell_folder"),
)

imported_roots = Table(
    "imported_roots",
    metadata,
    Column("root", Text, primary_key=True),  # host:absolute path of a runs root whose folders were read in
    Column("time", UTCDateTime, nullable=False),
)
