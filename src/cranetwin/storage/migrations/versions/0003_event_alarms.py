"""Alarm state of events: ``event_alarms`` (acknowledged / cleared, when and by whom).

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Create ``event_alarms`` (one row per acknowledged or cleared event)."""
    op.create_table(
        "event_alarms",
        sa.Column("event_id", sa.Integer(), nullable=False),
        sa.Column("acked_s", sa.Float(), nullable=True),
        sa.Column("acked_by", sa.String(length=200), nullable=True),
        sa.Column("cleared_s", sa.Float(), nullable=True),
        sa.Column("cleared_by", sa.String(length=200), nullable=True),
        sa.ForeignKeyConstraint(["event_id"], ["events.id"], ondelete="CASCADE",
                                name=op.f("fk_event_alarms_event_id_events")),
        sa.PrimaryKeyConstraint("event_id", name=op.f("pk_event_alarms")),
    )


def downgrade() -> None:
    """Drop ``event_alarms``."""
    op.drop_table("event_alarms")
