"""Registered machines: identity on the wire, model, HMAC secret, metadata, last known status.

The secret is needed to verify datagrams, so it is stored; it is never part of
:class:`MachineInfo` (what listings and the API see) and never logged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import BigInteger, Float, Integer, LargeBinary, String, Text, select
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.errors import StorageError
from cranetwin.storage.base import Base

WIRE_ID_MAX = 2**32 - 1


class UnknownMachineError(StorageError):
    """No machine is registered under the given id."""


class MachineRow(Base):
    """One registered machine."""

    __tablename__ = "machines"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    machine_id: Mapped[str] = mapped_column(String(128), unique=True)
    wire_id: Mapped[int] = mapped_column(BigInteger, unique=True)
    model: Mapped[str] = mapped_column(Text, default="patu655")
    secret: Mapped[bytes] = mapped_column(LargeBinary)
    meta_json: Mapped[str] = mapped_column(Text, default="{}")
    last_seen_ns: Mapped[int | None] = mapped_column(BigInteger, nullable=True)  # status only
    latitude_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    longitude_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    altitude_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    operating_hours: Mapped[float | None] = mapped_column(Float, nullable=True)
    status_ns: Mapped[int | None] = mapped_column(BigInteger, nullable=True)


@dataclass(frozen=True)
class MachineInfo:
    """What is public about a machine (no secret).

    Attributes:
        machine_id: Identifier used everywhere above the wire.
        wire_id: 32-bit id carried in datagrams.
        model: Built-in machine name (``patu655``) or the machine description as TOML text.
        metadata: Free-form JSON object (owner, site, serial number, ...).
        last_seen_s: Time of the newest stored sample or status [s since the epoch, machine
            clock], or None if nothing was received yet.
        latitude_deg, longitude_deg, altitude_m: Last reported GPS position, or None.
        operating_hours: Last reported operating-hours counter [h], or None.
        payload_version: Version of its stored known payload
            (:mod:`cranetwin.storage.payload_version`) when this was read, where read
            (:meth:`cranetwin.storage.Store.get_machine`); None in listings.
        newest_block_ns: End of its newest stored block [ns since the epoch], or None.
        late_version: Its late-data version (:mod:`cranetwin.storage.late_version`) when
            this was read, read with ``newest_block_ns`` (:meth:`cranetwin.storage.Store.
            get_machine`); None in listings.
    """

    machine_id: str
    wire_id: int
    model: str
    metadata: dict[str, Any] = field(default_factory=dict)
    last_seen_s: float | None = None
    latitude_deg: float | None = None
    longitude_deg: float | None = None
    altitude_m: float | None = None
    operating_hours: float | None = None
    payload_version: int | None = None
    newest_block_ns: int | None = None
    late_version: int | None = None


def to_info(row: MachineRow, newest_block_ns: int | None = None,
            payload_version: int | None = None,
            late_version: int | None = None) -> MachineInfo:
    """Public view of a machine row (drops the secret).

    Args:
        row: The machine row.
        newest_block_ns: End of the machine's newest stored block [ns], if any.
        payload_version: Version of its stored known payload, if read.
        late_version: Its late-data version, if read (with ``newest_block_ns``).
    """
    seen = [t for t in (row.last_seen_ns, newest_block_ns) if t is not None]
    return MachineInfo(
        machine_id=row.machine_id, wire_id=int(row.wire_id), model=row.model,
        metadata=json.loads(row.meta_json or "{}"),
        last_seen_s=max(seen) / 1e9 if seen else None,
        latitude_deg=row.latitude_deg, longitude_deg=row.longitude_deg,
        altitude_m=row.altitude_m, operating_hours=row.operating_hours,
        payload_version=payload_version, newest_block_ns=newest_block_ns,
        late_version=late_version,
    )


def check_new(machine_id: str, wire_id: int, secret: bytes) -> None:
    """Validate a machine to be registered.

    Raises:
        StorageError: Empty id, wire id outside [0, 2**32 − 1], or a secret shorter than 16 bytes.
    """
    if not machine_id or len(machine_id) > 128:
        raise StorageError(f"machine id must be 1..128 characters, got {machine_id!r}")
    if not 0 <= wire_id <= WIRE_ID_MAX:
        raise StorageError(f"wire id must be in [0, {WIRE_ID_MAX}], got {wire_id}")
    if len(secret) < 16:
        raise StorageError(f"secret must be at least 16 bytes, got {len(secret)}")


def get_row(session: Session, machine_id: str) -> MachineRow:
    """The row of ``machine_id``.

    Raises:
        UnknownMachineError: No such machine.
    """
    row = session.scalars(select(MachineRow).where(MachineRow.machine_id == machine_id)).first()
    if row is None:
        raise UnknownMachineError(f"no machine {machine_id!r} is registered; add it first "
                                  "(cranetwin machines add)")
    return row
