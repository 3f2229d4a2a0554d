"""The webhook outbox: ``webhook_outbox`` (deliveries waiting, done or given up) and
``webhook_cursor`` (the newest event id considered), see :mod:`cranetwin.storage.webhook_outbox`.

Revision ID: 0005w
Revises: 0005
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0005w"
down_revision: str | None = "0005"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Create ``webhook_outbox`` and ``webhook_cursor``."""
    op.create_table(
        "webhook_outbox",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("delivery_id", sa.String(length=64), nullable=False),
        sa.Column("body", sa.Text(), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("created_s", sa.Float(), nullable=False),
        sa.Column("next_attempt_s", sa.Float(), nullable=False),
        sa.Column("lease_until_s", sa.Float(), nullable=False),
        sa.Column("done_s", sa.Float(), nullable=True),
        sa.Column("last_error", sa.String(length=200), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_webhook_outbox")),
        sa.UniqueConstraint("delivery_id", name=op.f("uq_webhook_outbox_delivery_id")),
    )
    op.create_index("ix_webhook_outbox_state_next", "webhook_outbox",
                    ["state", "next_attempt_s"])
    op.create_table(
        "webhook_cursor",
        sa.Column("name", sa.String(length=32), nullable=False),
        sa.Column("event_id", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_webhook_cursor")),
    )


def downgrade() -> None:
    """Drop ``webhook_cursor`` and ``webhook_outbox``."""
    op.drop_table("webhook_cursor")
    op.drop_index("ix_webhook_outbox_state_next", table_name="webhook_outbox")
    op.drop_table("webhook_outbox")
