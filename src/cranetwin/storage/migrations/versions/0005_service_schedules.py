"""Service schedules per machine (``service_schedules``): maintenance items with an interval on
one basis (operating hours, lifts, damage fraction, calendar days), when they were last done, and
the claim of their ``service_due`` event (see cranetwin.storage.schedules).

Revision ID: 0005
Revises: 0004p
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004p"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Create ``service_schedules``."""
    op.create_table(
        "service_schedules",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("machine_pk", sa.Integer(), nullable=False),
        sa.Column("item", sa.String(length=200), nullable=False),
        sa.Column("basis", sa.String(length=32), nullable=False),
        sa.Column("interval", sa.Float(), nullable=False),
        sa.Column("detail", sa.String(length=128), nullable=True),
        sa.Column("last_done_value", sa.Float(), nullable=False),
        sa.Column("last_done_s", sa.Float(), nullable=False),
        sa.Column("last_done_by", sa.String(length=200), nullable=True),
        sa.Column("created_s", sa.Float(), nullable=False),
        sa.Column("created_by", sa.String(length=200), nullable=False),
        sa.Column("due_raised_s", sa.Float(), nullable=True),
        sa.Column("due_event_id", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(["machine_pk"], ["machines.id"], ondelete="CASCADE",
                                name=op.f("fk_service_schedules_machine_pk_machines")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_service_schedules")),
        sa.UniqueConstraint("machine_pk", "item", name="uq_service_schedules_machine_pk_item"),
    )


def downgrade() -> None:
    """Drop ``service_schedules``."""
    op.drop_table("service_schedules")
