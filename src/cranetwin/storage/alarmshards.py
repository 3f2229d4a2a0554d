"""Alarms over every shard (:mod:`cranetwin.storage.shards`): lists merged newest first, ids
that name their shard, new events found per shard.

An event's row id is unique only in its database, so the id an alarm carries above storage is
``local id × S + shard`` for S shards (:func:`global_id`); with one database (S = 1) it is the
row id itself. :func:`act` sends an acknowledgement to the shard the id names.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Literal

from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session

from cranetwin.storage import alarms as alarms_mod
from cranetwin.storage.alarms import Alarm
from cranetwin.storage.events import EventRow


def global_id(local: int, shard: int, shards: int) -> int:
    """The id of row ``local`` of shard ``shard`` among ``shards``."""
    return int(local) * shards + shard


def split_id(gid: int, shards: int) -> tuple[int, int]:
    """(shard, local row id) of a :func:`global_id`."""
    return gid % shards, gid // shards


def _tagged(a: Alarm, shard: int, shards: int) -> Alarm:
    return a if shards == 1 else replace(a, event_id=global_id(a.event_id, shard, shards))


def list_all(engines: Sequence[Engine], *, machine_ids: Sequence[str] | None = None,
             severities: Sequence[str] | None = None, kinds: Sequence[str] | None = None,
             t0_s: float | None = None, t1_s: float | None = None, state: str = "active",
             limit: int = 50, offset: int = 0) -> tuple[int, list[Alarm], list[str]]:
    """:func:`cranetwin.storage.alarms.list_alarms` over every engine: (how many match in all,
    the page newest first, every event kind in use). Each shard is asked for its newest
    ``offset + limit`` matches."""
    n = len(engines)
    total = 0
    rows: list[Alarm] = []
    kinds_all: set[str] = set()
    for i, e in enumerate(engines):
        with Session(e) as s:
            t, got = alarms_mod.list_alarms(s, machine_ids=machine_ids, severities=severities,
                                            kinds=kinds, t0_s=t0_s, t1_s=t1_s, state=state,
                                            limit=offset + limit, offset=0)
            kinds_all.update(alarms_mod.kinds_in_use(s))
        total += t
        rows.extend(_tagged(a, i, n) for a in got)
    rows.sort(key=lambda a: (a.t_s, a.event_id), reverse=True)
    return total, rows[offset:offset + limit], sorted(kinds_all)


def act(engines: Sequence[Engine], gid: int, action: Literal["acknowledge", "clear"], by: str,
        now_s: float) -> Alarm | None:
    """Acknowledge or clear the event ``gid`` on its shard; None when there is no such event."""
    n = len(engines)
    shard, local = split_id(gid, n)
    with Session(engines[shard]) as s, s.begin():
        a = alarms_mod.set_alarm_state(s, local, action, by, now_s)
    return None if a is None else _tagged(a, shard, n)


def newest_ids(engines: Sequence[Engine]) -> list[int]:
    """The newest event row id of each engine (0 when none)."""
    out = []
    for e in engines:
        with Session(e) as s:
            out.append(int(s.scalar(select(func.max(EventRow.id))) or 0))
    return out


def new_since(engines: Sequence[Engine], marks: Sequence[int], severities: Sequence[str],
              limit: int = 500) -> tuple[list[Alarm], list[int]]:
    """Events of ``severities`` stored after ``marks`` (one row id per engine), in the order
    each shard stored them, at most ``limit`` per shard; and the new marks (past every event
    seen, whatever its severity)."""
    n = len(engines)
    found: list[Alarm] = []
    out: list[int] = []
    for i, (e, last) in enumerate(zip(engines, marks, strict=True)):
        with Session(e) as s:
            top = int(s.scalar(select(func.max(EventRow.id))) or 0)
            ids = list(s.scalars(select(EventRow.id).where(
                EventRow.id > last, EventRow.id <= top, EventRow.severity.in_(list(severities)))
                .order_by(EventRow.id).limit(limit)))
            for k in ids:
                a = alarms_mod.get_alarm(s, k)
                if a is not None:
                    found.append(_tagged(a, i, n))
        out.append(ids[-1] if len(ids) == limit else top)
    return found, out
