"""What the twin worker reads once per pass for all the machines it owns, instead of once per
machine: the stored data ranges, the progress rows, on PostgreSQL the late-data marks and the
late blocks behind each watermark (:meth:`cranetwin.service.worker.TwinWorker._redo_late`;
without the blocks the worker's last pass saw, :class:`~cranetwin.storage.analytics_windows.
Seen`), the redo requests of a known payload stored or deleted, and the time ranges of the
stored known-payload runs (a span outside them reads none).

A pass over 500 machines then costs a handful of statements for these instead of seven per
machine; the new late-data marks are written in one statement at the end of the pass
(:func:`flush_marks`). The reads are taken at the start of the pass, in this order: data ranges,
then the commit-order mark (``pg_snapshot_xmin``), so a block that commits after the mark starts
after the newest sample the pass processes up to (as when each machine read its own). They are
only valid while the worker keeps the partitions it owned when it read them: the worker drops
them when its ownership changes in the pass and reads per machine for the rest of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cranetwin.storage import analytics_windows as aw
from cranetwin.storage import redo as redo_mod
from cranetwin.storage.redo import RedoRequest

if TYPE_CHECKING:
    from cranetwin.samples import SampleArrays
    from cranetwin.service.backend import Backend, Progress


@dataclass
class PassReads:
    """The pass's reads of the machines it owned when it started.

    Attributes:
        ranges: Machine → (first, last) stored sample time [s], or None (nothing stored).
        progress: Machine → stored progress (machines without a progress row left out).
        late: Machine → (stored mark, this pass's mark, late blocks [(t_start s, t_end s)])
            (PostgreSQL; a machine left out is read alone, e.g. one with a mark of the
            earlier kind).
        samples: Machine → (from s, to s, its samples read for [from, to)): the first span
            the pass expects to replay (taken by the machine's turn if it asks for the same
            range; it reads alone otherwise).
        payload: Machine → (first, last) time [s] of its stored known payload runs (machines
            without any left out): a span outside it reads none (:meth:`payload_stored`).
        marks: Machine → mark to store at the end of the pass (filled while processing).
        redo: Machine → its redo requests (:mod:`cranetwin.storage.redo`: a known payload
            stored or deleted), read for every machine with samples (one left out has none).
        snapshots: Machine → the snapshot whose xmin is this pass's mark (in :attr:`late`;
            what the worker remembers of a pass whose spans it committed, :class:`~cranetwin.
            storage.analytics_windows.Seen`).
    """

    ranges: dict[str, tuple[float, float] | None]
    progress: dict[str, Progress]
    late: dict[str, tuple[int | None, int, list[tuple[float, float]]]]
    redo: dict[str, list[RedoRequest]] = field(default_factory=dict)
    samples: dict[str, tuple[float, float, SampleArrays]] = field(default_factory=dict)
    payload: dict[str, tuple[float, float]] = field(default_factory=dict)
    marks: dict[str, int] = field(default_factory=dict)
    snapshots: dict[str, str] = field(default_factory=dict)

    def payload_stored(self, machine_id: str, t0_s: float, t1_s: float) -> bool:
        """Whether a known payload may be stored for [t0_s, t1_s] of the machine: False only
        when the pass read the machine's payload runs and none reaches into that span (its
        replay then reads none). Only for a machine whose late blocks the pass read too
        (:attr:`late`): the payload runs are read after that commit-order mark, so a block
        stored later, whose payload this read may not have seen, is late data of the next
        pass; a machine that reads its own mark later could mark such a block done."""
        if machine_id not in self.late:
            return True
        got = self.payload.get(machine_id)
        return got is not None and got[0] <= t1_s and got[1] >= t0_s


MAX_PREFETCH_S = 30.0
"""Longest first span whose samples the pass reads ahead [s] (bounds the memory of a pass
that catches up: 500 machines × 30 s × 10 Hz × 20 channels ≈ 24 MB)."""


def read_pass(backend: Backend, machine_ids: list[str], window_s: float,
              first_span: Callable[[float, float], tuple[float, float] | None] | None = None,
              seen: dict[str, tuple[int, aw.Seen, float]] | None = None,
              got: dict[str, tuple[int, tuple[float, float] | None]] | None = None,
              ) -> PassReads:
    """The reads of a pass over ``machine_ids`` (a few statements per engine).

    Args:
        backend: Store adapter.
        machine_ids: The machines the pass processes.
        window_s: The worker's window [s] (the watermark of a machine without progress).
        first_span: (watermark, newest sample) → the sample range [from, to) [s] of the first
            span the machine's turn will replay, None when nothing is ready (None: no samples
            read ahead).
        seen: Machine → (the mark its last pass stored, what that pass saw, the watermark it
            committed): used when the machine's stored mark and watermark are still those
            (no other worker moved them), so the blocks it saw are not late data now.
        got: :meth:`Backend.data_ranges` of ``machine_ids`` if already read this pass (the
            module docstring's order holds: they were read first).
    """
    if got is None:
        got = backend.data_ranges(machine_ids)
    else:
        got = {m: got[m] for m in machine_ids if m in got}
    ranges = {m: v[1] for m, v in got.items()}
    stored = [m for m, r in ranges.items() if r is not None]
    progress = backend.progress_many(stored) if stored else {}
    late: dict[str, tuple[int | None, int, list[tuple[float, float]]]] = {}
    snapshots: dict[str, str] = {}
    seen = seen or {}
    for engine, ids in backend.store.engines_of(stored):
        if engine.dialect.name != "postgresql":
            continue
        marks = aw.block_marks(engine, ids)
        top, snap = aw.snapshot(engine)  # after the data ranges (module docstring)
        bounds: dict[int, tuple[int, float]] = {}
        saw: dict[int, aw.Seen] = {}
        for m in ids:
            mark, legacy = marks[m]
            if legacy:
                continue
            if mark is None:
                late[m] = (None, top, [])
                continue
            p = progress.get(m)
            r = ranges[m]
            assert r is not None
            wm = p.watermark_s if p is not None else math.floor(r[0] / window_s) * window_s
            bounds[got[m][0]] = (mark, wm)
            last = seen.get(m)
            if last is not None and last[0] == mark and p is not None and last[2] == wm:
                saw[got[m][0]] = last[1]
        found = aw.new_blocks_before_many(engine, bounds, top, saw)
        by_pk = {got[m][0]: m for m in ids}
        for pk, (mark, _wm) in bounds.items():
            late[by_pk[pk]] = (mark, top, found.get(pk, []))
        snapshots.update(dict.fromkeys(ids, snap))
    redo: dict[str, list[RedoRequest]] = {}
    for engine, ids in backend.store.engines_of(stored):  # after the progress rows (a
        redo.update(redo_mod.pending(engine, ids))        # request read after a commit)
    reads = PassReads(ranges, progress, late, redo,
                      payload=_payload_ranges(backend, got, stored), snapshots=snapshots)
    if first_span is not None:
        _read_samples(backend, reads, got, window_s, first_span)
    return reads


def idle_machines(backend: Backend, got: dict[str, tuple[int, tuple[float, float] | None]],
                  known: dict[str, tuple[int, float]],
                  seen: dict[str, tuple[int, aw.Seen, float]]) -> set[str]:
    """Of the machines in ``known``, those with neither late blocks nor redo requests now
    (PostgreSQL; machines on other engines are left out): two statements per engine.

    The pass skips every other read for them when their next window is not ready either
    (:meth:`cranetwin.service.worker.TwinWorker._idle`). This is a trigger, not the redo
    itself: a machine it leaves out gets the full reads of :func:`read_pass`, which decide
    what is late with the stored mark. So a false alarm costs one machine's full reads, and
    nothing may be missed: the blocks looked at are those written by transactions in
    [known mark, this snapshot's xmin) that start before the known watermark, the same
    query as :func:`read_pass`'s with the worker's own record instead of the stored rows.

    Args:
        backend: Store adapter.
        got: This pass's :meth:`Backend.data_ranges` (machine → (primary key, range)).
        known: Machine → (the late-data mark [commit order] below which every block has been
            checked, the watermark [s] this worker committed): what the worker's last full
            reads of the machine and its later checks left (kept in memory only while the
            worker owns the machine). A check that finds nothing advances the mark in
            ``known`` to this snapshot's xmin (the stored mark stays: the full reads use it).
        seen: As :func:`read_pass`'s ``seen`` (used when its watermark is still the known).
    """
    ids = [m for m in known if m in got and got[m][1] is not None]
    out: set[str] = set()
    for engine, part in backend.store.engines_of(ids):
        if engine.dialect.name != "postgresql":
            continue
        top = aw.snapshot_xmin(engine)  # after the data ranges (module docstring)
        bounds = {got[m][0]: known[m] for m in part}
        saw = {got[m][0]: seen[m][1] for m in part
               if m in seen and seen[m][2] == known[m][1]}
        late = aw.new_blocks_before_many(engine, bounds, top, saw)
        asked = redo_mod.pending(engine, part)
        for m in part:
            if got[m][0] not in late and m not in asked:
                out.add(m)
                known[m] = (top, known[m][1])
    return out


def _payload_ranges(backend: Backend, got: dict[str, tuple[int, tuple[float, float] | None]],
                    ids: list[str]) -> dict[str, tuple[float, float]]:
    """Per machine, (first, last) time [s] of its stored known payload runs, one statement per
    engine. Read after the data ranges and the late blocks: the importer stores a block's
    payload before the block, so every block those reads saw has its payload seen here (a
    block stored after them is late data of the next pass, replayed again then)."""
    from sqlalchemy.orm import Session

    from cranetwin.storage.payloads import stored_ranges

    out: dict[str, tuple[float, float]] = {}
    for engine, part in backend.store.engines_of(ids):
        with Session(engine) as s:
            found = stored_ranges(s, [got[m][0] for m in part])
        for m in part:
            r = found.get(got[m][0])
            if r is not None:
                out[m] = (r[0] / 1e9, r[1] / 1e9)
    return out


def _read_samples(backend: Backend, reads: PassReads,
                  got: dict[str, tuple[int, tuple[float, float] | None]], window_s: float,
                  first_span: Callable[[float, float], tuple[float, float] | None]) -> None:
    """The samples of each machine's first span, one statement per engine."""
    from sqlalchemy.orm import Session

    from cranetwin.storage import blocks
    from cranetwin.storage.store import assemble_samples, sample_bounds_ns

    want: dict[str, tuple[float, float]] = {}
    for m, r in reads.ranges.items():
        if r is None:
            continue
        p = reads.progress.get(m)
        wm = p.watermark_s if p is not None else math.floor(r[0] / window_s) * window_s
        span = first_span(wm, r[1])
        if span is not None and span[1] - span[0] <= MAX_PREFETCH_S:
            want[m] = span
    for engine, ids in backend.store.engines_of(list(want)):
        ns = {m: sample_bounds_ns(*want[m]) for m in ids}
        with Session(engine) as s:
            stored = blocks.read_ranges(s, {got[m][0]: (a, z - 1) for m, (a, z) in ns.items()})
        for m in ids:
            a, z = ns[m]
            reads.samples[m] = (*want[m], assemble_samples(m, stored[got[m][0]], a, z))


def flush_marks(backend: Backend, reads: PassReads) -> None:
    """Store the marks the pass moved (one statement per engine)."""
    from sqlalchemy.orm import Session

    marks = dict(reads.marks)
    for engine, ids in backend.store.engines_of(list(marks)):
        rows = [aw.mark_row(engine.dialect.name, m, marks[m]) for m in ids]
        with Session(engine) as s, s.begin():
            aw.put_rows(s, rows)
    reads.marks.clear()
