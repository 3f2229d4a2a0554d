"""Ranges whose derived data the twin worker must compute again: a known payload stored or
deleted for samples it may already have processed.

The twin worker finds samples stored behind its progress mark by its block mark
(:func:`cranetwin.storage.analytics_windows.new_blocks_before`, late data). A known payload
(:mod:`cranetwin.storage.payloads`) changes no sample block, so storing or deleting one also
records the time range it changes here, in the same transaction: one row of
``analytics_windows`` (where the worker keeps its other marks) at level :data:`REDO_LEVEL` per
range, ``t0_ns``/``t1_ns`` its first and last changed time [ns] (both inclusive, like a
block's ``t_start_ns``/``t_end_ns``), ``n`` a version raised by every request on the same
start. The worker treats each range like a late block (its windows, and those whose replay
margin reaches into it, are redone: :meth:`cranetwin.service.worker.TwinWorker._redo_late`)
and then deletes the rows it read, each only if its version is still the one read: a request
recorded while the redo ran stays and is redone at the next pass. A range ahead of the
worker's mark needs nothing (its windows are replayed with the payload when they come) and is
deleted the same way.

Changed times less than :data:`MERGE_GAP_NS` apart are recorded as one range: an import of
blocks with a payload makes one row per stretch of blocks, not one per block.

An operator's request (:func:`request_whole`, ``cranetwin worker redo``: after the machine's
description changed, or to retry windows that failed before failed spans were recorded) is a
row at level :data:`WHOLE_LEVEL`, with the same columns and the same version rule. It covers
every window inside its range that holds stored samples (:func:`sampled_windows`) — processed,
failed or never processed (one the progress mark passed with nothing stored for it) — not
only the processed ones, and no neighbour by the replay margin: what is asked is the range.
The two kinds are kept apart (a payload's request on the same start never narrows an
operator's), read together (:func:`pending`) and deleted each by its own version
(:func:`done`).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from sqlalchemy import Engine, and_, delete, func, or_, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from cranetwin.storage.analytics_windows import SEC, AnalyticsWindowRow

REDO_LEVEL = -4
"""``level_s`` of a redo request (``-1`` duty to date, ``-2`` commit-order mark, ``-3`` lift
seconds, ``0`` block mark)."""
WHOLE_LEVEL = -8
"""``level_s`` of an operator's redo request (``-5`` known-payload version, ``-6`` failed span,
``-7`` late-data version)."""
MERGE_GAP_NS = 60 * SEC
"""Changed times at most this far apart [ns] are requested as one range."""


@dataclass(frozen=True)
class RedoRequest:
    """A range of one machine to process again.

    Attributes:
        t0_ns: First changed time [ns since the Unix epoch].
        t1_ns: Last changed time [ns] (inclusive; ≥ ``t0_ns``).
        version: Raised by every request recorded on the same ``t0_ns``.
        whole: An operator's request (every window of the range holding samples), not a
            known payload's (the processed windows it changes and their neighbours).
    """

    t0_ns: int
    t1_ns: int
    version: int
    whole: bool = False

    @property
    def level(self) -> int:
        """The request's ``level_s``."""
        return WHOLE_LEVEL if self.whole else REDO_LEVEL

    @property
    def span_s(self) -> tuple[float, float]:
        """(first, last) changed time [s since the Unix epoch]."""
        return self.t0_ns / SEC, self.t1_ns / SEC


def merged(spans_ns: Iterable[tuple[int, int]], gap_ns: int = MERGE_GAP_NS
           ) -> list[tuple[int, int]]:
    """``spans_ns`` [(first, last) ns, inclusive] sorted and joined where at most ``gap_ns``
    apart."""
    out: list[tuple[int, int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in spans_ns):
        if out and a - out[-1][1] <= gap_ns:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def request(session: Session, machine_id: str, spans_ns: Iterable[tuple[int, int]]) -> int:
    """Record that the derived data of ``spans_ns`` [(first, last) ns, inclusive] must be
    computed again, inside the caller's transaction (the one storing or deleting the payload);
    returns the rows written. A request on a start already recorded widens it to the larger
    end and raises its version."""
    spans = merged(spans_ns)
    _upsert(session, machine_id, REDO_LEVEL, spans)
    return len(spans)


def request_whole(session: Session, machine_id: str, t0_ns: int, t1_ns: int) -> RedoRequest:
    """Record an operator's request to process again every window of [t0_ns, t1_ns] [ns,
    inclusive] that holds stored samples, inside the caller's transaction; returns it as
    stored (a request on a start already recorded is widened to the larger end, its version
    raised).

    Raises:
        ValueError: ``t1_ns`` before ``t0_ns``.
    """
    if t1_ns < t0_ns:
        raise ValueError(f"a redo range ends ({t1_ns} ns) before it starts ({t0_ns} ns)")
    _upsert(session, machine_id, WHOLE_LEVEL, [(t0_ns, t1_ns)])
    w = AnalyticsWindowRow
    b, n = session.execute(select(w.t1_ns, w.n).where(
        w.machine_id == machine_id, w.level_s == WHOLE_LEVEL, w.t0_ns == t0_ns)).one()
    return RedoRequest(t0_ns, int(b), int(n), whole=True)


def _upsert(session: Session, machine_id: str, level: int,
            spans: Sequence[tuple[int, int]]) -> None:
    """Insert the requests ``spans`` of ``level``; one on a start already recorded widens it
    to the larger end and raises its version."""
    if not spans:
        return
    w = AnalyticsWindowRow
    dialect = session.connection().dialect.name
    ins = (postgresql.insert(w) if dialect == "postgresql" else sqlite.insert(w)).values(
        [{"machine_id": machine_id, "level_s": level, "t0_ns": a, "t1_ns": b, "n": 1,
          "data": b"", "operating_s": 0.0, "idle_s": 0.0} for a, b in spans])
    bigger = (func.greatest if dialect == "postgresql" else func.max)(w.t1_ns,
                                                                     ins.excluded.t1_ns)
    session.execute(ins.on_conflict_do_update(
        index_elements=["machine_id", "level_s", "t0_ns"],
        set_={"t1_ns": bigger, "n": w.n + 1}))


def pending(engine: Engine, machine_ids: Sequence[str]) -> dict[str, list[RedoRequest]]:
    """The requests of ``machine_ids``, of both kinds (one statement per 1000 machines):
    machine → requests, oldest start first (machines without any left out)."""
    w = AnalyticsWindowRow
    out: dict[str, list[RedoRequest]] = {}
    ids = list(machine_ids)
    with Session(engine) as s:
        for i in range(0, len(ids), 1000):
            for mid, level, a, b, n in s.execute(
                    select(w.machine_id, w.level_s, w.t0_ns, w.t1_ns, w.n)
                    .where(w.machine_id.in_(ids[i:i + 1000]),
                           w.level_s.in_((REDO_LEVEL, WHOLE_LEVEL)))
                    .order_by(w.machine_id, w.t0_ns, w.level_s)):
                out.setdefault(str(mid), []).append(
                    RedoRequest(int(a), int(b), int(n), whole=level == WHOLE_LEVEL))
    return out


def done(engine: Engine, machine_id: str, requests: Sequence[RedoRequest]) -> int:
    """Delete ``requests`` of a machine that still have the version read (module docstring);
    returns how many were."""
    if not requests:
        return 0
    w = AnalyticsWindowRow
    with Session(engine) as s, s.begin():
        res = s.execute(delete(w).where(
            w.machine_id == machine_id, w.level_s.in_((REDO_LEVEL, WHOLE_LEVEL)),
            or_(*[and_(w.level_s == r.level, w.t0_ns == r.t0_ns, w.n == r.version)
                  for r in requests])))
        return int(getattr(res, "rowcount", 0) or 0)


def sampled_windows(engine: Engine, machine_id: str, t0_ns: int, t1_ns: int,
                    window_s: float) -> list[float]:
    """Starts [s] of the windows (``window_s`` long, aligned to multiples of it, as the twin
    worker's) that overlap [t0_ns, t1_ns] [ns, inclusive] and a stored block of the machine,
    oldest first (a block's span stands for its samples: a window inside a gap within a block
    is included). Reads the blocks' times only, not their samples."""
    from cranetwin.storage.blocks import spans
    from cranetwin.storage.machines import MachineRow

    with Session(engine) as s:
        pk = s.scalar(select(MachineRow.id).where(MachineRow.machine_id == machine_id))
        if pk is None:
            return []
        got = spans(s, int(pk), t0_ns, t1_ns)
    win_ns = round(window_s * SEC)
    first, last = t0_ns // win_ns, t1_ns // win_ns
    out: list[int] = []
    for a, b in got:  # ordered by start; a long block may reach past the next ones
        lo, hi = max(first, a // win_ns), min(last, b // win_ns)
        if out and lo <= out[-1]:
            lo = out[-1] + 1
        out.extend(range(lo, hi + 1))
    return [k * window_s for k in out]


@dataclass(frozen=True)
class RangeSurvey:
    """The windows of an operator's request (:func:`survey`): counts of windows holding stored
    samples.

    Attributes:
        processed: Behind the watermark, inside a span with a stored part.
        failed: Behind the watermark, inside a failed span
            (:mod:`cranetwin.storage.failed_windows`).
        never: Behind the watermark, inside neither (passed with nothing stored).
        ahead: At or past the watermark (processed forward when they come).
    """

    processed: int
    failed: int
    never: int
    ahead: int


def survey(engine: Engine, machine_id: str, t0_ns: int, t1_ns: int, window_s: float,
           watermark_s: float | None) -> RangeSurvey:
    """What a request for [t0_ns, t1_ns] [ns, inclusive] covers (:func:`sampled_windows`)
    against the watermark ``watermark_s`` [s] (None: nothing processed yet)."""
    from cranetwin.storage.analytics_windows import spans
    from cranetwin.storage.failed_windows import failed_spans

    wins = sampled_windows(engine, machine_id, t0_ns, t1_ns, window_s)
    behind = [w for w in wins if watermark_s is not None and w + window_s <= watermark_s]
    if not behind:
        return RangeSurvey(0, 0, 0, len(wins))
    reach = max(60.0, window_s)
    lo, hi = behind[0] - reach, behind[-1] + window_s + reach

    def inside(w: float, stored: list[tuple[float, float]]) -> bool:
        i = bisect.bisect_right(stored, (w, math.inf)) - 1
        return i >= 0 and stored[i][0] <= w < stored[i][1]

    parts = spans(engine, machine_id, 60, lo, hi)
    failed = failed_spans(engine, machine_id, lo, hi)
    n_part = sum(inside(w, parts) for w in behind)
    n_failed = sum(not inside(w, parts) and inside(w, failed) for w in behind)
    return RangeSurvey(n_part, n_failed, len(behind) - n_part - n_failed,
                       len(wins) - len(behind))


__all__ = ["MERGE_GAP_NS", "REDO_LEVEL", "WHOLE_LEVEL", "RangeSurvey", "RedoRequest", "done",
           "merged", "pending", "request", "request_whole", "sampled_windows", "survey"]
