# ruff: noqa: E501
"""Initial schema: machines, sample_blocks, summaries, summary_dirty, events.

Revision ID: 0001
Revises:
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    """Upgrade schema."""
    op.create_table('machines',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('machine_id', sa.String(length=128), nullable=False),
    sa.Column('wire_id', sa.BigInteger(), nullable=False),
    sa.Column('model', sa.Text(), nullable=False),
    sa.Column('secret', sa.LargeBinary(), nullable=False),
    sa.Column('meta_json', sa.Text(), nullable=False),
    sa.Column('last_seen_ns', sa.BigInteger(), nullable=True),
    sa.Column('latitude_deg', sa.Float(), nullable=True),
    sa.Column('longitude_deg', sa.Float(), nullable=True),
    sa.Column('altitude_m', sa.Float(), nullable=True),
    sa.Column('operating_hours', sa.Float(), nullable=True),
    sa.Column('status_ns', sa.BigInteger(), nullable=True),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_machines')),
    sa.UniqueConstraint('machine_id', name=op.f('uq_machines_machine_id')),
    sa.UniqueConstraint('wire_id', name=op.f('uq_machines_wire_id'))
    )
    op.create_table('events',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('machine_pk', sa.Integer(), nullable=False),
    sa.Column('t_ns', sa.BigInteger(), nullable=False),
    sa.Column('kind', sa.String(length=64), nullable=False),
    sa.Column('severity', sa.String(length=16), nullable=False),
    sa.Column('evidence_json', sa.Text(), nullable=False),
    sa.ForeignKeyConstraint(['machine_pk'], ['machines.id'], name=op.f('fk_events_machine_pk_machines'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_events')),
    sa.UniqueConstraint('machine_pk', 't_ns', 'kind', name=op.f('uq_events_machine_pk_t_ns_kind'))
    )
    with op.batch_alter_table('events', schema=None) as batch_op:
        batch_op.create_index('ix_events_machine_t', ['machine_pk', 't_ns'], unique=False)

    op.create_table('sample_blocks',
    sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'), autoincrement=True, nullable=False),
    sa.Column('machine_pk', sa.Integer(), nullable=False),
    sa.Column('seq', sa.BigInteger(), nullable=False),
    sa.Column('t_start_ns', sa.BigInteger(), nullable=False),
    sa.Column('t_end_ns', sa.BigInteger(), nullable=False),
    sa.Column('period_ns', sa.BigInteger(), nullable=False),
    sa.Column('n', sa.Integer(), nullable=False),
    sa.Column('channels', sa.Text(), nullable=False),
    sa.Column('resolution', sa.Text(), nullable=False),
    sa.Column('summary', sa.LargeBinary(), nullable=False),
    sa.Column('data', sa.LargeBinary(), nullable=False),
    sa.ForeignKeyConstraint(['machine_pk'], ['machines.id'], name=op.f('fk_sample_blocks_machine_pk_machines'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_sample_blocks')),
    sa.UniqueConstraint('machine_pk', 'seq', name=op.f('uq_sample_blocks_machine_pk_seq'))
    )
    with op.batch_alter_table('sample_blocks', schema=None) as batch_op:
        batch_op.create_index('ix_sample_blocks_machine_t_end', ['machine_pk', 't_end_ns'], unique=False)
        batch_op.create_index('ix_sample_blocks_machine_t_start', ['machine_pk', 't_start_ns'], unique=False)

    op.create_table('summary_dirty',
    sa.Column('machine_pk', sa.Integer(), nullable=False),
    sa.Column('minute_s', sa.BigInteger(), nullable=False),
    sa.Column('version', sa.BigInteger(), nullable=False),
    sa.ForeignKeyConstraint(['machine_pk'], ['machines.id'], name=op.f('fk_summary_dirty_machine_pk_machines'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('machine_pk', 'minute_s', name=op.f('pk_summary_dirty'))
    )
    op.create_table('summaries',
    sa.Column('machine_pk', sa.Integer(), nullable=False),
    sa.Column('channel', sa.String(length=64), nullable=False),
    sa.Column('level_s', sa.Integer(), nullable=False),
    sa.Column('bucket_s', sa.BigInteger(), nullable=False),
    sa.Column('n', sa.BigInteger(), nullable=False),
    sa.Column('vmin', sa.Float(), nullable=False),
    sa.Column('vmax', sa.Float(), nullable=False),
    sa.Column('vsum', sa.Float(), nullable=False),
    sa.ForeignKeyConstraint(['machine_pk'], ['machines.id'], name=op.f('fk_summaries_machine_pk_machines'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('machine_pk', 'channel', 'level_s', 'bucket_s', name=op.f('pk_summaries'))
    )


def downgrade() -> None:
    """Downgrade schema."""
    op.drop_table('summaries')
    op.drop_table('summary_dirty')
    with op.batch_alter_table('sample_blocks', schema=None) as batch_op:
        batch_op.drop_index('ix_sample_blocks_machine_t_start')
        batch_op.drop_index('ix_sample_blocks_machine_t_end')

    op.drop_table('sample_blocks')
    with op.batch_alter_table('events', schema=None) as batch_op:
        batch_op.drop_index('ix_events_machine_t')

    op.drop_table('events')
    op.drop_table('machines')
