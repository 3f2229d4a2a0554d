"""PostgreSQL: every ``sample_blocks`` row records the transaction that wrote it (``writer_xid``).

The twin worker finds late blocks by a mark over the blocks it has seen. Block ids come from a
sequence when the insert runs, not when it commits, so with concurrent writers a lower id can
commit after a higher one was seen. ``writer_xid`` (``xid8``, default ``pg_current_xact_id()``)
lets a pass take only rows whose transaction is below ``pg_snapshot_xmin(pg_current_snapshot())``:
every transaction below that has ended, so no row can appear below the mark later
(:func:`cranetwin.storage.analytics_windows.new_blocks_before`).

Rows stored before this revision get ``writer_xid`` 0 (committed long ago): the column is added
with the constant default (no table rewrite, also on the partitioned table of ``0004p``, where it
reaches every partition), then the default becomes ``pg_current_xact_id()`` for new rows. An
index on (machine_pk, writer_xid) serves the worker's query.

SQLite has one writer at a time (ids grow in commit order): nothing to do.

Revision ID: 0006c
Revises: 0005w
Create Date: 2026-12-02
"""

from __future__ import annotations

from alembic import op

revision: str = "0006c"
down_revision: str | None = "0005w"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Add ``sample_blocks.writer_xid`` (PostgreSQL only)."""
    if op.get_bind().dialect.name != "postgresql":
        return
    op.execute("ALTER TABLE sample_blocks ADD COLUMN writer_xid xid8 NOT NULL DEFAULT '0'")
    op.execute("ALTER TABLE sample_blocks ALTER COLUMN writer_xid "
               "SET DEFAULT pg_current_xact_id()")
    op.execute("CREATE INDEX ix_sample_blocks_machine_writer_xid "
               "ON sample_blocks (machine_pk, writer_xid)")


def downgrade() -> None:
    """Drop ``sample_blocks.writer_xid`` (PostgreSQL only)."""
    if op.get_bind().dialect.name != "postgresql":
        return
    op.execute("DROP INDEX IF EXISTS ix_sample_blocks_machine_writer_xid")
    op.execute("ALTER TABLE sample_blocks DROP COLUMN writer_xid")
