"""Names and settings of the fleet bus: stream, subjects, partitions, message ids, consumers.

A block of machine ``m`` (sender epoch ``e``, sequence ``s``) is published to subject
``<prefix>.<p>.<m>`` with ``p = crc32(m) mod P`` (:func:`partition_of`; stable across
processes, hosts and Python versions) and header ``Nats-Msg-Id: m/e/s`` (:func:`msg_id_of`),
so JetStream drops a retransmission within the stream's duplicate window. The stream is a
work queue on file storage: a message is deleted once its partition's storage writer has acked
it (after the database commit), and when the stream is full (``max_msgs``) a publish is refused
rather than an old message dropped, so a stalled storage writer holds the daemons back (they stop
acknowledging and the machines keep their data) instead of losing data. See ``docs/BUS.md``.
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass
from typing import Any

from cranetwin.errors import StorageError
from cranetwin.storage.nats_loop import nats_module

_TOKEN_OK = re.compile(r"[A-Za-z0-9_-]+")


@dataclass(frozen=True)
class BusConfig:
    """Settings of the fleet bus (the same on every daemon and storage writer).

    Attributes:
        url: NATS server, ``nats://host:port``.
        stream: JetStream stream name.
        prefix: Subject prefix; the stream holds ``<prefix>.>`` (two deployments, or tests, on
            one server use different prefixes and stream names).
        partitions: Number of partitions P (machines are spread by :func:`partition_of`);
            changing it moves machines between partitions: drain the stream first.
        duplicate_window_s: JetStream's deduplication window [s]: a message id seen within it
            is dropped (PubAck ``duplicate``). Must exceed the time over which a daemon may
            publish the same block again (see docs/BUS.md; storage's (machine, epoch, seq)
            uniqueness catches anything older).
        max_msgs: Stream size limit [messages = blocks]; when full, publishes are refused (the
            daemons stop acknowledging) — nothing is ever discarded. A count, not bytes: on
            nats-server 2.9.10, ``max_bytes`` with ``discard: new`` was seen to drop old,
            acknowledged messages instead of refusing new ones (``tests/test_bus.py``).
        publish_timeout_s: Longest wait for the PubAcks of one batch [s]; past it the batch
            counts as not written (the daemon retries it, nothing acked).
        ack_wait_s: A message delivered to a storage writer and not acked within this time is
            delivered again (after a crash of the writer) [s].
        level: zlib level of the samples in a message (0: stored uncompressed, the
            delta/zigzag byte planes only; see :func:`cranetwin.bus.blockcodec.encode_blocks`).
    """

    url: str = "nats://127.0.0.1:4222"
    stream: str = "CRANETWIN_BLOCKS"
    prefix: str = "cranetwin.blocks"
    partitions: int = 16
    duplicate_window_s: float = 120.0
    max_msgs: int = 2_000_000
    publish_timeout_s: float = 2.0
    ack_wait_s: float = 30.0
    level: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.partitions <= 4096:
            raise StorageError(f"bus partitions must be in 1..4096, got {self.partitions}")
        if not all(_TOKEN_OK.fullmatch(t) for t in self.prefix.split(".")):
            raise StorageError(f"bus subject prefix {self.prefix!r}: dot-separated tokens of "
                               "letters, digits, _ and - expected")
        if not _TOKEN_OK.fullmatch(self.stream):
            raise StorageError(f"bus stream name {self.stream!r}: letters, digits, _ and - "
                               "expected")


def partition_of(machine_id: str, partitions: int) -> int:
    """The partition of a machine: CRC-32 of its UTF-8 id modulo ``partitions``."""
    return zlib.crc32(machine_id.encode()) % partitions


def subject_token(machine_id: str) -> str:
    """The machine id as one subject token: itself if it is letters, digits, ``_`` and ``-``,
    else every other byte as ``%XX`` (``.``, ``*``, ``>`` and spaces are special in NATS)."""
    if _TOKEN_OK.fullmatch(machine_id):
        return machine_id
    return "".join(ch if _TOKEN_OK.fullmatch(ch) else "".join(f"%{x:02X}" for x in ch.encode())
                   for ch in machine_id)


def subject_of(cfg: BusConfig, machine_id: str) -> str:
    """``<prefix>.<partition>.<machine token>``."""
    return f"{cfg.prefix}.{partition_of(machine_id, cfg.partitions)}.{subject_token(machine_id)}"


def partition_filter(cfg: BusConfig, partition: int) -> str:
    """Subject filter of one partition, ``<prefix>.<p>.*``."""
    return f"{cfg.prefix}.{partition}.*"


def msg_id_of(machine_id: str, epoch: int, seq: int) -> str:
    """``Nats-Msg-Id`` of a block: ``machine/epoch/seq`` (storage's idempotency key)."""
    return f"{machine_id}/{epoch}/{seq}"


def durable_name(cfg: BusConfig, partition: int) -> str:
    """Durable consumer name of the storage writer of ``partition``."""
    return f"store-writer-{partition}"


def deliver_subject(cfg: BusConfig, partition: int) -> str:
    """Where the storage writer consumer of ``partition`` delivers (outside the stream's
    subjects)."""
    return f"_cranetwin.deliver.{cfg.stream}.{partition}"


async def ensure_stream(js: Any, cfg: BusConfig) -> None:
    """Create the stream if it does not exist (an existing one is left as it is).

    Args:
        js: A nats-py ``JetStreamContext``.
    """
    nats = nats_module()
    api = nats.js.api
    try:
        await js.stream_info(cfg.stream)
        return
    except nats.js.errors.NotFoundError:
        pass
    try:
        await js.add_stream(api.StreamConfig(
            name=cfg.stream, subjects=[f"{cfg.prefix}.>"],
            retention=api.RetentionPolicy.WORK_QUEUE, storage=api.StorageType.FILE,
            discard=api.DiscardPolicy.NEW, max_msgs=cfg.max_msgs,
            duplicate_window=cfg.duplicate_window_s,
            description="cranetwin sample blocks, one message per block"))
    except nats.js.errors.BadRequestError:  # created meanwhile by another process
        await js.stream_info(cfg.stream)
