"""Writing a batch of sample blocks so that one bad block never fails the others.

:meth:`cranetwin.storage.Store.write_batch` returns a :class:`WriteResult`: per input block
whether it was newly stored, was already stored (a duplicate: durable, may be acked) or is
refused, with a reason that never changes on a retry:

``seq_reused``
    A block with the same (machine, epoch, seq) but a different t_start, n or period is stored.
``overlap``
    The block's time range [t0, t_end] intersects a stored block of the same machine with a
    different (epoch, seq), or an earlier block of the same batch. Stored blocks of a machine
    never overlap, so every timestamp is stored at most once and raw reads (``/samples``) and
    summaries (``/history``) count the same samples.
``unstorable``
    The block breaks a storage limit (:func:`cranetwin.storage.blocks.check_block`: times
    outside [0, 2262-04-10), a span over 6 h, non-finite values, out-of-range integers, ...) or
    the database rejects its values (data or integrity error).
``unknown_machine``
    No machine is registered under the block's machine id.

A batch that carries one (machine, epoch, seq) twice (the same datagram received twice) gives
the second copy the first one's outcome (``duplicate`` if the first is durable), or
``seq_reused`` if the two differ in t_start, n or period.

How (:func:`write`): cheap checks and the compression first, per block; then one transaction
that probes, for all blocks in one statement, the stored block with the same key and a stored
block overlapping in time (two index probes per block), inserts the rest with ``ON CONFLICT DO
NOTHING``, marks their minutes for the summary rollup and records them in the machines'
late-data versions (:func:`cranetwin.storage.late_version.note`: a block stored behind the
newest one raises it; the replay cache depends on it). Should that transaction still fail with
a data or integrity error, the batch is bisected in transactions that are rolled back, down to
the blocks that fail alone; those are refused and one last transaction stores all the others.
Only one transaction commits, so when :class:`~cranetwin.errors.StorageUnavailableError`
(database unreachable, connection lost, locked too long) or another
:class:`~cranetwin.errors.StorageError` is raised, nothing of the call was stored.

The overlap probe relies on stored blocks not overlapping each other (so the stored block with
the smallest t_end ≥ t0 is the only one that can start before t0 and reach into the new block);
rows stored before this rule existed may overlap, and a new block overlapping only such rows
can then be missed by it. The check assumes one writer per machine at a time (the ingest
daemon): two processes writing the same machine concurrently could both pass it.
"""

from __future__ import annotations

import bisect
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal

from sqlalchemy.orm import Session

from cranetwin.errors import StorageError
from cranetwin.samples import SampleBlock
from cranetwin.storage import blocks as blocks_mod
from cranetwin.storage import late_version
from cranetwin.storage import summaries as summaries_mod
from cranetwin.storage.dberrors import is_data_error, is_unavailable, unavailable

log = logging.getLogger(__name__)

Status = Literal["stored", "duplicate", "refused", "unavailable"]
REASONS = ("seq_reused", "overlap", "unstorable", "unknown_machine")
"""Every refusal reason :class:`BlockOutcome` may carry."""


@dataclass(frozen=True)
class BlockOutcome:
    """What became of one block of a batch.

    Attributes:
        status: ``stored`` (newly stored by this call), ``duplicate`` (the same block was already
            stored: same (machine, epoch, seq), t_start, n and period), ``refused`` (not
            stored, and never will be on a retry) or ``unavailable`` (not stored because the
            database shard of its machine failed while the others were written
            (:class:`cranetwin.storage.shards.ShardedStore`): neither acknowledge nor refuse
            it; a retry may store it).
        reason: For ``refused``: one of :data:`REASONS`; :data:`UNAVAILABLE` for
            ``unavailable``; None otherwise.
        detail: One line for the logs (why it was refused); empty otherwise.
    """

    status: Status
    reason: str | None = None
    detail: str = ""

    @property
    def durable(self) -> bool:
        """The block is in the database (stored now or before): it may be acknowledged."""
        return self.status in ("stored", "duplicate")


UNAVAILABLE = "shard_unavailable"
"""The reason of an ``unavailable`` outcome."""

STORED = BlockOutcome("stored")
DUPLICATE = BlockOutcome("duplicate")


def unavailable_outcome(detail: str) -> BlockOutcome:
    """Not stored: the machine's shard failed (retry later; neither ack nor refuse)."""
    return BlockOutcome("unavailable", UNAVAILABLE, detail)


def refused(reason: str, detail: str) -> BlockOutcome:
    """A refusal with ``reason`` (one of :data:`REASONS`)."""
    assert reason in REASONS, reason
    return BlockOutcome("refused", reason, detail)


@dataclass(frozen=True)
class WriteResult:
    """Outcome of :meth:`cranetwin.storage.Store.write_batch`, one entry per input block.

    Attributes:
        blocks: The input blocks, in input order.
        outcomes: ``outcomes[i]`` belongs to ``blocks[i]``.
    """

    blocks: tuple[SampleBlock, ...]
    outcomes: tuple[BlockOutcome, ...]

    def __len__(self) -> int:
        return len(self.blocks)

    def __iter__(self) -> Iterator[tuple[SampleBlock, BlockOutcome]]:
        return iter(zip(self.blocks, self.outcomes, strict=True))

    @property
    def new(self) -> list[SampleBlock]:
        """Blocks newly stored by this call (for live fan-out), in input order."""
        return [b for b, o in self if o.status == "stored"]

    @property
    def durable(self) -> list[SampleBlock]:
        """Blocks that are stored, now or before (the ones that may be acknowledged)."""
        return [b for b, o in self if o.durable]

    @property
    def refused(self) -> list[tuple[SampleBlock, BlockOutcome]]:
        """Blocks refused, with their outcome (``reason``, ``detail``); an ``unavailable``
        block is not among them (see :attr:`unavailable`)."""
        return [(b, o) for b, o in self if o.status == "refused"]

    @property
    def unavailable(self) -> list[tuple[SampleBlock, BlockOutcome]]:
        """Blocks not stored because their shard failed: retry them, neither ack nor refuse."""
        return [(b, o) for b, o in self if o.status == "unavailable"]

    def counts(self) -> dict[str, int]:
        """Number of blocks per ``stored``, ``duplicate`` and per refusal reason (non-zero only)."""
        out: dict[str, int] = {}
        for o in self.outcomes:
            k = o.reason if o.reason is not None else o.status
            out[k] = out.get(k, 0) + 1
        return out


# -- the write -------------------------------------------------------------------------------
@dataclass
class Pending:
    """A block that passed the checks and is compressed, waiting for the transaction.

    Attributes:
        i: Index in the caller's batch.
        pk: Machine primary key.
        block: The block.
        row: Column values (:data:`cranetwin.storage.blocks.COLUMNS` order).
    """

    i: int
    pk: int
    block: SampleBlock
    row: tuple[object, ...]
    key: tuple[int, int, int] = field(init=False)
    shape: tuple[int, int, int] = field(init=False)
    t_end: int = field(init=False)

    def __post_init__(self) -> None:
        b = self.block
        self.key = (self.pk, int(b.epoch), int(b.seq))
        self.shape = (int(b.t0_ns), b.n, int(b.period_ns))
        self.t_end = self.shape[0] + (self.shape[1] - 1) * self.shape[2]


def prepare(blocks: Sequence[SampleBlock], pks: dict[str, int],
            outcomes: list[BlockOutcome | None]) -> list[Pending]:
    """Cheap checks and compression; fills ``outcomes`` for the refused blocks.

    Args:
        blocks: The batch.
        pks: Machine id → primary key of the registered machines among the blocks'.
        outcomes: One slot per block, None = not decided yet.
    """
    todo: list[tuple[int, int, SampleBlock]] = []
    for i, b in enumerate(blocks):
        pk = pks.get(b.machine_id) if isinstance(b.machine_id, str) else None
        if pk is None:
            outcomes[i] = refused("unknown_machine",
                                  f"no machine {b.machine_id!r} is registered")
            continue
        why = blocks_mod.check_block(b)
        if why is not None:
            outcomes[i] = refused("unstorable", why)
            continue
        todo.append((i, pk, b))
    rows = blocks_mod.block_rows([(pk, b) for _, pk, b in todo])
    out = []
    for (i, pk, b), row in zip(todo, rows, strict=True):
        if isinstance(row, str):
            outcomes[i] = refused("unstorable", row)
        else:
            out.append(Pending(i, pk, b, row))
    return out


def _attempt(factory: Callable[[], Session], items: Sequence[Pending],
             commit: bool) -> dict[int, BlockOutcome]:
    """One transaction over ``items`` (distinct keys): probe, insert, mark the minutes dirty,
    note the late-data versions; committed if ``commit``, else rolled back (a trial for the
    bisection). Raises the database's error unchanged."""
    out: dict[int, BlockOutcome] = {}
    with factory() as s:
        try:
            s.begin()
            hits = blocks_mod.probe(s.connection(), [
                (j, it.pk, it.key[1], it.key[2], it.shape[0], it.t_end)
                for j, it in enumerate(items)])
            candidates: list[Pending] = []
            for j, it in enumerate(items):
                h = hits.get(j)
                if h is not None and h.same_key is not None:
                    out[it.i] = (DUPLICATE if h.same_key == it.shape else refused(
                        "seq_reused", _reused(it, h.same_key)))
                elif h is not None and h.overlap is not None:
                    out[it.i] = refused("overlap", f"samples [{it.shape[0]}, {it.t_end}] ns "
                                        f"overlap the stored block epoch {h.overlap[0]} seq "
                                        f"{h.overlap[1]}")
                else:
                    candidates.append(it)
            accepted = _drop_overlaps_within(candidates, out)
            new = blocks_mod.insert_new(s, [it.row for it in accepted])
            raced = [it for it in accepted if it.key not in new]
            if raced:  # stored by someone else since the probe: classify against theirs
                shapes = blocks_mod.stored_shapes(s, [it.key for it in raced])
                for it in raced:
                    got = shapes.get(it.key)
                    if got is None:
                        raise StorageError(f"block {it.key} was neither inserted nor found")
                    out[it.i] = (DUPLICATE if got == it.shape
                                 else refused("seq_reused", _reused(it, got)))
            minutes: set[tuple[int, int]] = set()
            spans: dict[str, tuple[int, int, int]] = {}
            for it in accepted:
                if it.key in new:
                    out[it.i] = STORED
                    minutes.update(summaries_mod.block_minutes(it.pk, it.shape[0], it.t_end))
                    mid = str(it.block.machine_id)
                    _, a, z = spans.get(mid, (it.pk, it.shape[0], it.t_end))
                    spans[mid] = (it.pk, min(a, it.shape[0]), max(z, it.t_end))
            summaries_mod.mark_dirty(s, minutes)
            late_version.note(s, [(m, *v) for m, v in spans.items()])
            if commit:
                s.commit()
            else:
                s.rollback()
        except BaseException:
            s.rollback()
            raise
    return out


def _reused(it: Pending, stored: tuple[int, int, int]) -> str:
    return (f"epoch {it.key[1]} seq {it.key[2]} is stored with t0 {stored[0]} ns, n {stored[1]}, "
            f"period {stored[2]} ns; this block has t0 {it.shape[0]} ns, n {it.shape[1]}, "
            f"period {it.shape[2]} ns")


def _drop_overlaps_within(items: Sequence[Pending],
                          out: dict[int, BlockOutcome]) -> list[Pending]:
    """The blocks that overlap no earlier one of ``items`` (same machine); the others are
    refused in ``out``."""
    spans: dict[int, tuple[list[int], list[int], list[Pending]]] = {}
    keep = []
    for it in items:
        starts, ends, owners = spans.setdefault(it.pk, ([], [], []))
        t0, t1 = it.shape[0], it.t_end
        p = bisect.bisect_left(starts, t0)
        other = None
        if p > 0 and ends[p - 1] >= t0:
            other = owners[p - 1]
        elif p < len(starts) and starts[p] <= t1:
            other = owners[p]
        if other is not None:
            out[it.i] = refused("overlap", f"samples [{t0}, {t1}] ns overlap block epoch "
                                f"{other.key[1]} seq {other.key[2]} of the same batch")
            continue
        starts.insert(p, t0)
        ends.insert(p, t1)
        owners.insert(p, it)
        keep.append(it)
    return keep


def _rejected(exc: BaseException) -> str:
    return f"the database rejected it: {str(exc).splitlines()[0]}"


def _isolate(factory: Callable[[], Session], items: Sequence[Pending],
             exc: BaseException) -> dict[int, str]:
    """Blocks of ``items`` (a set that failed with the data error ``exc``) that fail on their
    own, found by bisection in rolled-back transactions; index → the database's error."""
    if len(items) == 1:
        return {items[0].i: _rejected(exc)}
    bad: dict[int, str] = {}
    mid = len(items) // 2
    for half in (items[:mid], items[mid:]):
        try:
            _attempt(factory, half, commit=False)
        except Exception as err:
            if is_unavailable(err):
                raise unavailable(f"storing {len(items)} block(s)", err) from err
            if not is_data_error(err):
                raise _storage_error(len(items), err) from err
            bad.update(_isolate(factory, half, err))
    return bad


def _run(factory: Callable[[], Session], items: list[Pending]) -> dict[int, BlockOutcome]:
    """Store ``items`` (distinct keys) in one committed transaction, isolating blocks the
    database rejects."""
    if not items:
        return {}
    try:
        return _attempt(factory, items, commit=True)
    except Exception as exc:
        if is_unavailable(exc):
            raise unavailable(f"storing {len(items)} block(s)", exc) from exc
        if not is_data_error(exc):
            raise _storage_error(len(items), exc) from exc
        first = exc
    bad = _isolate(factory, items, first)
    for i, why in bad.items():
        log.warning("block %d of the batch refused: %s", i, why)
    good = [it for it in items if it.i not in bad]
    try:
        out = _attempt(factory, good, commit=True) if good else {}
    except Exception as exc:
        if is_unavailable(exc):
            raise unavailable(f"storing {len(items)} block(s)", exc) from exc
        first_line = str(first).splitlines()[0]
        raise StorageError(f"could not store {len(items)} block(s): the batch fails but no "
                           f"block fails alone ({first_line}); nothing stored") from exc
    for i, why in bad.items():
        out[i] = refused("unstorable", why)
    return out


def _storage_error(n: int, exc: BaseException) -> StorageError:
    """``exc`` as the StorageError to raise (a new one naming the batch size)."""
    return StorageError(f"could not store {n} block(s), nothing stored: {type(exc).__name__}: "
                        f"{exc}".splitlines()[0])


def write(factory: Callable[[], Session], blocks: Sequence[SampleBlock],
          pks: dict[str, int]) -> WriteResult:
    """The body of :meth:`cranetwin.storage.Store.write_batch` (see the module docstring).

    Args:
        factory: New sessions on the store's engine.
        blocks: The batch, any machines.
        pks: Machine id → primary key, for every registered machine among the blocks'.
    """
    outcomes: list[BlockOutcome | None] = [None] * len(blocks)
    pending = prepare(blocks, pks, outcomes)
    first: dict[tuple[int, int, int], Pending] = {}
    repeats: list[Pending] = []
    for it in pending:
        if it.key in first:
            repeats.append(it)
        else:
            first[it.key] = it
    for i, got in _run(factory, list(first.values())).items():
        outcomes[i] = got
    for it in repeats:  # one key twice in a batch (the same datagram twice): as its first copy
        head = first[it.key]
        o = outcomes[head.i]
        assert o is not None
        if head.shape != it.shape:
            outcomes[it.i] = refused("seq_reused", f"the batch carries epoch {it.key[1]} seq "
                                     f"{it.key[2]} twice, with different t0, n or period")
        else:
            outcomes[it.i] = DUPLICATE if o.durable else o
    if any(o is None for o in outcomes):  # a bug: refuse rather than report a block durable
        log.error("write_batch left %d block(s) undecided", sum(o is None for o in outcomes))
    final = tuple(o if o is not None else refused("unstorable", "internal error: undecided")
                  for o in outcomes)
    return WriteResult(tuple(blocks), final)
