"""The webhook outbox: alarm notifications waiting to be POSTed, kept in the database.

``webhook_outbox`` has one row per delivery (``delivery_id``: the event id, unique, so an alarm
is queued once however many processes offer it), the exact body to POST (a retry sends the same
bytes), its state (``pending``, ``delivered``, ``failed``), the attempts made, when the next one
is due and until when a sender holds it (``lease_until_s``). ``webhook_cursor`` keeps the newest
event id already considered, so the alarm check that queues new events continues after a
restart where it stopped. Revision ``0005w_webhook_outbox``.

A sender claims due rows with a conditional update (``lease_until_s`` in the past → now + lease):
of several processes exactly one wins a row; one killed while it held a row leaves it pending,
and once the lease has run out the next claim sends it again (at least once). Times are seconds
since the epoch on the claiming process's clock.

Functions take a SQLAlchemy ``Session``; the caller commits (like :mod:`cranetwin.storage.alarms`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from sqlalchemy import BigInteger, Float, Index, Integer, String, Text, delete, func, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.storage.base import Base

Outcome = Literal["delivered", "failed", "retry"]
PENDING, DELIVERED, FAILED = "pending", "delivered", "failed"


class WebhookOutboxRow(Base):
    """One queued webhook delivery."""

    __tablename__ = "webhook_outbox"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    delivery_id: Mapped[str] = mapped_column(String(64), unique=True)
    body: Mapped[str] = mapped_column(Text)
    state: Mapped[str] = mapped_column(String(16), default=PENDING)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    created_s: Mapped[float] = mapped_column(Float)
    next_attempt_s: Mapped[float] = mapped_column(Float)
    lease_until_s: Mapped[float] = mapped_column(Float, default=0.0)
    done_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    last_error: Mapped[str | None] = mapped_column(String(200), nullable=True)

    __table_args__ = (Index("ix_webhook_outbox_state_next", "state", "next_attempt_s"),)


class WebhookCursorRow(Base):
    """The newest event id the alarm check has considered for the webhook."""

    __tablename__ = "webhook_cursor"

    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    event_id: Mapped[int] = mapped_column(BigInteger)


@dataclass(frozen=True)
class OutboxItem:
    """A claimed delivery.

    Attributes:
        id: Row id.
        delivery_id: The ``X-Cranetwin-Delivery`` value (the event id).
        body: The JSON body to POST (UTF-8 text).
        attempts: The number of this attempt (1 for the first; counted when claimed, so an
            attempt cut short by a crash counts).
    """

    id: int
    delivery_id: str
    body: str
    attempts: int


def _insert(session: Session) -> postgresql.Insert | sqlite.Insert:
    bind = session.get_bind()
    if bind.dialect.name == "postgresql":
        return postgresql.insert(WebhookOutboxRow)
    return sqlite.insert(WebhookOutboxRow)


def enqueue(session: Session, items: Sequence[tuple[str, str]], now_s: float) -> None:
    """Queue ``(delivery_id, body)`` pairs, due now; a delivery id already queued (by this or
    another process, in any state) is left as it is."""
    if not items:
        return
    rows = [{"delivery_id": d, "body": b, "state": PENDING, "attempts": 0, "created_s": now_s,
             "next_attempt_s": now_s, "lease_until_s": 0.0} for d, b in items]
    session.execute(_insert(session).values(rows)
                    .on_conflict_do_nothing(index_elements=["delivery_id"]))


def cursor(session: Session, name: str = "events") -> int | None:
    """The event id stored under ``name``, or None before the first :func:`advance_cursor`."""
    v = session.scalar(select(WebhookCursorRow.event_id).where(WebhookCursorRow.name == name))
    return None if v is None else int(v)


def advance_cursor(session: Session, event_id: int, name: str = "events") -> None:
    """Move the cursor ``name`` to ``event_id`` (never backwards: several processes may race)."""
    bind = session.get_bind()
    ins = (postgresql.insert(WebhookCursorRow) if bind.dialect.name == "postgresql"
           else sqlite.insert(WebhookCursorRow))
    new = func.max(WebhookCursorRow.event_id, event_id) if bind.dialect.name == "sqlite" else \
        func.greatest(WebhookCursorRow.event_id, event_id)
    session.execute(ins.values(name=name, event_id=event_id)
                    .on_conflict_do_update(index_elements=["name"], set_={"event_id": new}))


def claim(session: Session, now_s: float, lease_s: float, limit: int = 20) -> list[OutboxItem]:
    """Take up to ``limit`` due pending rows (oldest first) whose lease has run out, holding
    each until ``now_s + lease_s`` and counting the attempt about to be made. A row another
    process claimed meanwhile is skipped."""
    r = WebhookOutboxRow
    due = session.execute(
        select(r.id, r.delivery_id, r.body, r.attempts)
        .where(r.state == PENDING, r.next_attempt_s <= now_s, r.lease_until_s <= now_s)
        .order_by(r.next_attempt_s, r.id).limit(limit)).all()
    out = []
    for row_id, delivery_id, body, attempts in due:
        res = session.execute(update(r).where(r.id == row_id, r.state == PENDING,
                                              r.lease_until_s <= now_s)
                              .values(lease_until_s=now_s + lease_s, attempts=r.attempts + 1))
        if getattr(res, "rowcount", 0) == 1:
            out.append(OutboxItem(int(row_id), str(delivery_id), str(body), int(attempts) + 1))
    return out


def finish(session: Session, row_id: int, outcome: Outcome, now_s: float,
           next_attempt_s: float | None = None, error: str | None = None) -> None:
    """Record the outcome of the claimed attempt on row ``row_id``: ``delivered``, ``failed``
    (given up) or ``retry`` (pending again, due at ``next_attempt_s``); the lease is
    released."""
    r = WebhookOutboxRow
    values: dict[str, object] = {"lease_until_s": 0.0,
                                 "last_error": None if error is None else error[:200]}
    if outcome == "retry":
        values["next_attempt_s"] = now_s if next_attempt_s is None else next_attempt_s
    else:
        values["state"] = DELIVERED if outcome == "delivered" else FAILED
        values["done_s"] = now_s
    session.execute(update(r).where(r.id == row_id).values(**values))


def release(session: Session, row_ids: Sequence[int]) -> None:
    """Give up the lease of rows claimed but not attempted (due again at once, the attempt not
    counted)."""
    if row_ids:
        r = WebhookOutboxRow
        session.execute(update(r).where(r.id.in_(list(row_ids)))
                        .values(lease_until_s=0.0, attempts=r.attempts - 1))


def next_due(session: Session) -> float | None:
    """When the earliest pending row is due (or its lease runs out) [s], or None."""
    r = WebhookOutboxRow
    v = session.scalar(select(func.min(func.max(r.next_attempt_s, r.lease_until_s)
                                       if session.get_bind().dialect.name == "sqlite" else
                                       func.greatest(r.next_attempt_s, r.lease_until_s)))
                       .where(r.state == PENDING))
    return None if v is None else float(v)


def counts(session: Session) -> dict[str, int]:
    """How many rows are in each state."""
    r = WebhookOutboxRow
    return {str(s): int(n) for s, n in session.execute(
        select(r.state, func.count()).group_by(r.state))}


def items(session: Session) -> list[tuple[str, str, int]]:
    """``(delivery_id, state, attempts)`` of every row, oldest first."""
    r = WebhookOutboxRow
    return [(str(d), str(s), int(a)) for d, s, a in session.execute(
        select(r.delivery_id, r.state, r.attempts).order_by(r.id))]


def purge(session: Session, before_s: float) -> int:
    """Delete delivered and failed rows finished before ``before_s``; returns how many."""
    r = WebhookOutboxRow
    res = session.execute(delete(r).where(r.state != PENDING, r.done_s < before_s))
    return int(getattr(res, "rowcount", 0) or 0)
