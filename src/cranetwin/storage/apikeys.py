"""API keys (hashed, with roles) and the twin worker's per-machine progress.

Owned by the API (``cranetwin.api``); kept here so that every table lives on the storage
package's declarative :class:`~cranetwin.storage.base.Base` and in its Alembic history
(revision ``*_api_keys.py``).

* ``api_keys``: one row per key — public ``key_id``, ``sha256`` of the secret (the secret itself
  is never stored), role (``viewer`` / ``fleet`` / ``admin``), name, creation and revocation times.
* ``twin_progress``: one row per machine — the twin worker's watermark (samples before it are
  summarised, so no window is processed twice) and the cumulative counters the ISO 15143-3
  snapshot reports (operating and idle time, lifts, payload totals, overloads).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from sqlalchemy import Boolean, Float, Integer, String, select
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.errors import StorageError
from cranetwin.storage.base import Base

ROLES = ("viewer", "fleet", "admin")


class ApiKeyRow(Base):
    """One API key (secret stored as its sha256 only)."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    key_id: Mapped[str] = mapped_column(String(32), unique=True)
    secret_sha256: Mapped[str] = mapped_column(String(64))
    role: Mapped[str] = mapped_column(String(16))
    name: Mapped[str] = mapped_column(String(200), default="")
    created_s: Mapped[float] = mapped_column(Float)
    revoked_s: Mapped[float | None] = mapped_column(Float, nullable=True)


class TwinProgressRow(Base):
    """The twin worker's state for one machine."""

    __tablename__ = "twin_progress"

    machine_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    watermark_s: Mapped[float] = mapped_column(Float)
    windows: Mapped[int] = mapped_column(Integer, default=0)
    operating_s: Mapped[float] = mapped_column(Float, default=0.0)
    idle_s: Mapped[float] = mapped_column(Float, default=0.0)
    load_count: Mapped[int] = mapped_column(Integer, default=0)
    payload_total_kg: Mapped[float] = mapped_column(Float, default=0.0)
    load_cube_sum: Mapped[float] = mapped_column(Float, default=0.0)
    overloads: Mapped[int] = mapped_column(Integer, default=0)
    max_payload_kg: Mapped[float] = mapped_column(Float, default=0.0)
    in_lift: Mapped[bool] = mapped_column(Boolean, default=False)
    lift_peak_kg: Mapped[float] = mapped_column(Float, default=0.0)
    lift_peak_ratio: Mapped[float] = mapped_column(Float, default=0.0)
    last_payload_kg: Mapped[float | None] = mapped_column(Float, nullable=True)
    theta0_rad: Mapped[float | None] = mapped_column(Float, nullable=True)
    updated_s: Mapped[float] = mapped_column(Float)


@dataclass(frozen=True)
class KeyInfo:
    """A stored key without its hash."""

    key_id: str
    role: str
    name: str
    created_s: float
    revoked_s: float | None


def add_key(session: Session, key_id: str, secret_sha256: str, role: str, name: str = "") -> None:
    """Store a new key (caller commits).

    Raises:
        StorageError: Unknown role, or a malformed hash.
    """
    if role not in ROLES:
        raise StorageError(f"unknown role {role!r}; expected one of {', '.join(ROLES)}")
    if len(secret_sha256) != 64:
        raise StorageError("secret_sha256 must be 64 hex digits")
    session.add(ApiKeyRow(key_id=key_id, secret_sha256=secret_sha256, role=role, name=name,
                          created_s=time.time(), revoked_s=None))


def active_key(session: Session, key_id: str) -> tuple[str, str, str] | None:
    """``(secret_sha256, name, role)`` of an unrevoked key, or None."""
    row = session.scalars(select(ApiKeyRow).where(ApiKeyRow.key_id == key_id)).first()
    if row is None or row.revoked_s is not None:
        return None
    return row.secret_sha256, row.name, row.role


def list_keys(session: Session) -> list[KeyInfo]:
    """Every key, oldest first."""
    rows = session.scalars(select(ApiKeyRow).order_by(ApiKeyRow.id)).all()
    return [KeyInfo(r.key_id, r.role, r.name, r.created_s, r.revoked_s) for r in rows]


def revoke_key(session: Session, key_id: str) -> bool:
    """Mark a key revoked (caller commits); False if there is no such key."""
    row = session.scalars(select(ApiKeyRow).where(ApiKeyRow.key_id == key_id)).first()
    if row is None:
        return False
    if row.revoked_s is None:
        row.revoked_s = time.time()
    return True


def get_progress(session: Session, machine_id: str) -> TwinProgressRow | None:
    """The worker's progress row of a machine, or None before its first window."""
    return session.get(TwinProgressRow, machine_id)
