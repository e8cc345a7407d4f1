"""The first results schema: runs, their per-region statistics, verification checks, imported runs roots.

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "runs",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("cell", sa.String(200), nullable=False),
        sa.Column("folder", sa.Text, nullable=False),
        sa.Column("recipe", sa.String(200), nullable=False),
        sa.Column("recipe_sha256", sa.String(64)),
        sa.Column("part", sa.String(200), nullable=False),
        sa.Column("serial", sa.String(64)),
        sa.Column("operator", sa.String(64)),
        sa.Column("production_order", sa.String(64)),
        sa.Column("started", sa.DateTime, nullable=False),
        sa.Column("finished", sa.DateTime),
        sa.Column("status", sa.String(32), nullable=False),
        sa.Column("verdict", sa.String(32)),
        sa.Column("n_points", sa.Integer),
        sa.Column("coverage", sa.Float),
        sa.Column("dev_min", sa.Float),
        sa.Column("dev_max", sa.Float),
        sa.Column("dev_mean", sa.Float),
        sa.Column("dev_std", sa.Float),
        sa.Column("tol_lower", sa.Float),
        sa.Column("tol_upper", sa.Float),
        sa.Column("recorded", sa.DateTime, nullable=False),
        sa.UniqueConstraint("cell", "folder", name="uq_runs_cell_folder"),
    )
    op.create_index("ix_runs_started", "runs", ["started"])
    op.create_index("ix_runs_part", "runs", ["part", "started"])
    op.create_index("ix_runs_recipe", "runs", ["recipe", "started"])
    op.create_index("ix_runs_serial", "runs", ["serial"])
    op.create_table(
        "run_regions",
        sa.Column("run_id", sa.Integer, sa.ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("name", sa.String(200), primary_key=True),
        sa.Column("kind", sa.String(16)),
        sa.Column("tol_lower", sa.Float),
        sa.Column("tol_upper", sa.Float),
        sa.Column("n_points", sa.Integer),
        sa.Column("n_out", sa.Integer),
        sa.Column("mean", sa.Float),
        sa.Column("min", sa.Float),
        sa.Column("max", sa.Float),
        sa.Column("coverage", sa.Float),
        sa.Column("verdict", sa.String(32)),
    )
    op.create_table(
        "verifications",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("cell", sa.String(200), nullable=False),
        sa.Column("folder", sa.Text, nullable=False),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("time", sa.DateTime, nullable=False),
        sa.Column("pf", sa.Float),
        sa.Column("ps", sa.Float),
        sa.Column("sd", sa.Float),
        sa.Column("f", sa.Float),
        sa.Column("verdict", sa.String(32), nullable=False),
        sa.UniqueConstraint("cell", "folder", name="uq_verifications_cell_folder"),
    )
    op.create_index("ix_verifications_cell_time", "verifications", ["cell", "time"])
    op.create_table(
        "imported_roots",
        sa.Column("root", sa.Text, primary_key=True),
        sa.Column("time", sa.DateTime, nullable=False),
    )


def downgrade() -> None:
    op.drop_table("imported_roots")
    op.drop_table("verifications")
    op.drop_table("run_regions")
    op.drop_table("runs")
