"""API keys (hashed, with roles) and the twin worker's per-machine progress.

Revision ID: 0001a
Revises: 0001
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0001a"
down_revision: str | None = "0001"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Create ``api_keys`` and ``twin_progress``."""
    op.create_table(
        "api_keys",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("key_id", sa.String(length=32), nullable=False),
        sa.Column("secret_sha256", sa.String(length=64), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("created_s", sa.Float(), nullable=False),
        sa.Column("revoked_s", sa.Float(), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_api_keys")),
        sa.UniqueConstraint("key_id", name=op.f("uq_api_keys_key_id")),
    )
    op.create_table(
        "twin_progress",
        sa.Column("machine_id", sa.String(length=128), nullable=False),
        sa.Column("watermark_s", sa.Float(), nullable=False),
        sa.Column("windows", sa.Integer(), nullable=False),
        sa.Column("operating_s", sa.Float(), nullable=False),
        sa.Column("idle_s", sa.Float(), nullable=False),
        sa.Column("load_count", sa.Integer(), nullable=False),
        sa.Column("payload_total_kg", sa.Float(), nullable=False),
        sa.Column("load_cube_sum", sa.Float(), nullable=False),
        sa.Column("overloads", sa.Integer(), nullable=False),
        sa.Column("max_payload_kg", sa.Float(), nullable=False),
        sa.Column("in_lift", sa.Boolean(), nullable=False),
        sa.Column("lift_peak_kg", sa.Float(), nullable=False),
        sa.Column("lift_peak_ratio", sa.Float(), nullable=False),
        sa.Column("last_payload_kg", sa.Float(), nullable=True),
        sa.Column("theta0_rad", sa.Float(), nullable=True),
        sa.Column("updated_s", sa.Float(), nullable=False),
        sa.PrimaryKeyConstraint("machine_id", name=op.f("pk_twin_progress")),
    )


def downgrade() -> None:
    """Drop both tables."""
    op.drop_table("twin_progress")
    op.drop_table("api_keys")
