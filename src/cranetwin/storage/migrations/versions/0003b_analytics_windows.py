"""Stored analytics parts per machine and window (``analytics_windows``).

Keyed on (machine_id, level_s, t0_ns); ``data`` holds the serialised analytics part of the
window (see cranetwin.storage.analytics_windows). The lead re-chains this revision after 0003
at merge (its down_revision then becomes "0003").

Revision ID: 0003b
Revises: 0002
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0003b"
down_revision: str | None = "0003"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Create ``analytics_windows``."""
    op.create_table(
        "analytics_windows",
        sa.Column("machine_id", sa.String(128), nullable=False),
        sa.Column("level_s", sa.Integer(), nullable=False),
        sa.Column("t0_ns", sa.BigInteger(), nullable=False),
        sa.Column("t1_ns", sa.BigInteger(), nullable=False),
        sa.Column("n", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.Column("operating_s", sa.Float(), nullable=False, server_default=sa.text("0")),
        sa.Column("idle_s", sa.Float(), nullable=False, server_default=sa.text("0")),
        sa.PrimaryKeyConstraint("machine_id", "level_s", "t0_ns", name="pk_analytics_windows"),
    )


def downgrade() -> None:
    """Drop ``analytics_windows``."""
    op.drop_table("analytics_windows")
