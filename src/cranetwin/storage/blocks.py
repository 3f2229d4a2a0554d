"""Raw samples, stored as compressed blocks: one row per received datagram, not one per sample.

A row holds one :class:`~cranetwin.samples.SampleBlock` (``n`` regularly spaced samples of one
machine) compressed by :mod:`cranetwin.storage.codec`. Rows are unique on (machine, seq), and
inserted with ``ON CONFLICT DO NOTHING`` on both dialects, so writing a block twice (a
retransmission, a replayed batch after a crash) stores it once.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from sqlalchemy import (
    BigInteger,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    Text,
    UniqueConstraint,
    select,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.samples import F64, SampleBlock
from cranetwin.storage import codec
from cranetwin.storage.base import Base


class BlockRow(Base):
    """A compressed run of samples of one machine (one datagram's worth)."""

    __tablename__ = "sample_blocks"
    __table_args__ = (
        UniqueConstraint("machine_pk", "seq"),
        Index("ix_sample_blocks_machine_t_start", "machine_pk", "t_start_ns"),
        Index("ix_sample_blocks_machine_t_end", "machine_pk", "t_end_ns"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    seq: Mapped[int] = mapped_column(BigInteger)
    t_start_ns: Mapped[int] = mapped_column(BigInteger)
    t_end_ns: Mapped[int] = mapped_column(BigInteger)
    period_ns: Mapped[int] = mapped_column(BigInteger)
    n: Mapped[int] = mapped_column(Integer)
    channels: Mapped[str] = mapped_column(Text)  # JSON list of names
    resolution: Mapped[str] = mapped_column(Text)  # JSON list of steps
    data: Mapped[bytes] = mapped_column(LargeBinary)


def block_params(machine_pk: int, block: SampleBlock) -> dict[str, object]:
    """Column values for one block (compresses its samples)."""
    return {
        "machine_pk": machine_pk, "seq": block.seq, "t_start_ns": block.t0_ns,
        "t_end_ns": block.t_end_ns, "period_ns": block.period_ns, "n": block.n,
        "channels": json.dumps(list(block.channels), separators=(",", ":")),
        "resolution": json.dumps(list(block.resolution), separators=(",", ":")),
        "data": codec.encode(block.values, block.resolution),
    }


def insert_new(session: Session, params: Sequence[dict[str, object]]) -> set[tuple[int, int]]:
    """Insert block rows, ignoring (machine, seq) already stored.

    Returns:
        The (machine_pk, seq) keys that were newly inserted.
    """
    if not params:
        return set()
    dialect = session.get_bind().dialect.name
    ins = postgresql.insert(BlockRow) if dialect == "postgresql" else sqlite.insert(BlockRow)
    stmt = ins.on_conflict_do_nothing(index_elements=["machine_pk", "seq"]).returning(
        BlockRow.machine_pk, BlockRow.seq)
    rows = session.execute(stmt, list(params)).all()
    return {(int(r[0]), int(r[1])) for r in rows}


@dataclass(frozen=True)
class StoredBlock:
    """A block read back from the table.

    Attributes:
        seq: Sequence number.
        t0_ns: First sample time [ns]; period_ns: sample period [ns].
        channels, resolution: Channel layout.
        values: Shape (n, len(channels)) [channel units].
    """

    seq: int
    t0_ns: int
    period_ns: int
    channels: tuple[str, ...]
    resolution: tuple[float, ...]
    values: F64

    def times_ns(self) -> npt.NDArray[np.int64]:
        """Sample times, shape (n,) [ns]."""
        return self.t0_ns + np.arange(self.values.shape[0], dtype=np.int64) * self.period_ns


def read_range(session: Session, machine_pk: int, t0_ns: int, t1_ns: int) -> list[StoredBlock]:
    """Blocks of a machine that overlap [t0_ns, t1_ns], ordered by start time."""
    stmt = (select(BlockRow.seq, BlockRow.t_start_ns, BlockRow.period_ns, BlockRow.channels,
                   BlockRow.resolution, BlockRow.data)
            .where(BlockRow.machine_pk == machine_pk, BlockRow.t_start_ns <= t1_ns,
                   BlockRow.t_end_ns >= t0_ns)
            .order_by(BlockRow.t_start_ns, BlockRow.seq))
    out = []
    for seq, t0, period, chans, res, data in session.execute(stmt):
        resolution = tuple(float(r) for r in json.loads(res))
        out.append(StoredBlock(int(seq), int(t0), int(period), tuple(json.loads(chans)),
                               resolution, codec.decode(data, resolution)))
    return out
