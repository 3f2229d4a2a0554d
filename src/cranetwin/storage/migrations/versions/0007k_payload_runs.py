"""A known payload as a stored time series: ``payload_runs`` (see
:mod:`cranetwin.storage.payloads`): one row per run of regularly spaced values of one machine,
keyed by (machine, t_start_ns), with an index on (machine, t_end_ns) for range reads.

A new table only: the rows of every other table are untouched (SQLite and PostgreSQL alike;
each shard of a sharded store is migrated on its own).

Revision ID: 0007k
Revises: 0006c
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0007k"
down_revision: str | None = "0006c"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Create ``payload_runs``."""
    op.create_table(
        "payload_runs",
        sa.Column("machine_pk", sa.Integer(), nullable=False),
        sa.Column("t_start_ns", sa.BigInteger(), nullable=False),
        sa.Column("t_end_ns", sa.BigInteger(), nullable=False),
        sa.Column("period_ns", sa.BigInteger(), nullable=False),
        sa.Column("n", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["machine_pk"], ["machines.id"], ondelete="CASCADE",
                                name=op.f("fk_payload_runs_machine_pk_machines")),
        sa.PrimaryKeyConstraint("machine_pk", "t_start_ns", name=op.f("pk_payload_runs")),
    )
    op.create_index("ix_payload_runs_machine_pk_t_end_ns", "payload_runs",
                    ["machine_pk", "t_end_ns"])


def downgrade() -> None:
    """Drop ``payload_runs``."""
    op.drop_index("ix_payload_runs_machine_pk_t_end_ns", table_name="payload_runs")
    op.drop_table("payload_runs")
