"""Block identity (machine, epoch, seq): ``sample_blocks.epoch``, the sender's boot id.

Adds ``epoch BIGINT NOT NULL DEFAULT 0`` (rows stored before it, from protocol version 1
senders, become epoch 0) and replaces the unique key (machine_pk, seq) by
(machine_pk, epoch, seq). SQLite rebuilds the table (batch mode, every row copied once);
PostgreSQL alters it in place (the new unique index is built once).

Revision ID: 0002
Revises: 0001a
Create Date: 2026-11-30
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001a"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Add ``epoch`` and key the blocks on (machine_pk, epoch, seq)."""
    with op.batch_alter_table("sample_blocks", schema=None) as batch_op:
        batch_op.add_column(sa.Column("epoch", sa.BigInteger(), nullable=False,
                                      server_default=sa.text("0")))
        batch_op.drop_constraint("uq_sample_blocks_machine_pk_seq", type_="unique")
        batch_op.create_unique_constraint("uq_sample_blocks_machine_pk_epoch_seq",
                                          ["machine_pk", "epoch", "seq"])


def downgrade() -> None:
    """Back to (machine_pk, seq); fails if two epochs of a machine reuse a sequence number."""
    with op.batch_alter_table("sample_blocks", schema=None) as batch_op:
        batch_op.drop_constraint("uq_sample_blocks_machine_pk_epoch_seq", type_="unique")
        batch_op.create_unique_constraint("uq_sample_blocks_machine_pk_seq",
                                          ["machine_pk", "seq"])
        batch_op.drop_column("epoch")
