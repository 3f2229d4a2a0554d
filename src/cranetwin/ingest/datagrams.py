"""The daemon's datagram path: datagrams in from the event loop, authenticated and decoded by
the protocol's :class:`~cranetwin.protocol.Receiver`, and the only replies the daemon sends
(acks after commit, refusals, re-acks of replays).

:class:`DatagramPath` is the base of :class:`~cranetwin.ingest.daemon.IngestDaemon`: it is the
only place that knows the Receiver's API and the only one that writes to the socket. Only an
authenticated datagram is ever answered (see :meth:`DatagramPath._decode`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import socket
import threading
from collections.abc import Callable
from typing import Any

from cranetwin.errors import CraneTwinError
from cranetwin.ingest.config import DaemonConfig
from cranetwin.ingest.keys import MachineKeys
from cranetwin.ingest.metrics import Metrics
from cranetwin.ingest.writer import is_unavailable
from cranetwin.protocol import (
    REFUSAL_CODES,
    TYPE_REFUSAL,
    DatagramError,
    Receiver,
    RefusedError,
    ReplayedError,
)
from cranetwin.protocol.status import StatusReport
from cranetwin.samples import SampleBlock

__all__ = ["Addr", "DatagramPath", "Item", "Raw"]

log = logging.getLogger("cranetwin.ingest.daemon")  # one logger for the daemon's messages

Addr = tuple[Any, ...]
Item = SampleBlock | StatusReport
Raw = tuple[bytes, Addr, int]  # a datagram, its sender's address, its receive time [ns]


def _is_refusal(datagram: bytes) -> bool:
    """Whether a datagram the daemon sends is a refusal (else an ack): its type byte."""
    return len(datagram) > 3 and datagram[3] == TYPE_REFUSAL


class DatagramPath:
    """Datagrams in, replies out (base of the daemon; its state is set by the daemon's
    ``__init__``)."""

    config: DaemonConfig
    metrics: Metrics
    keys: MachineKeys
    _receiver: Receiver
    _rx_lock: threading.Lock
    _queue: queue.Queue[list[Raw] | None]
    _gathering: list[Raw]
    _hand_over_at: asyncio.TimerHandle | None
    _accepted_in: int
    _taken_out: int
    _loop: asyncio.AbstractEventLoop | None
    _stopping: bool
    _clock: Callable[[], int]
    _sock: socket.socket | None
    _logged: set[str]
    _log_lock: threading.Lock

    # -- logging ------------------------------------------------------------------------------
    def _log_once(self, kind: str, exc: BaseException | None, msg: str, *args: Any) -> None:
        """Log ``msg`` the first time ``kind`` (plus the exception's type) happens; afterwards
        the counters say how often it recurs."""
        key = f"{kind}:{type(exc).__name__}" if exc is not None else kind
        with self._log_lock:
            if key in self._logged:
                return
            self._logged.add(key)
        expected = exc is None or isinstance(exc, CraneTwinError) or is_unavailable(exc)
        log.error(msg + " (logged once; see the counters for repeats)", *args,
                  exc_info=None if expected else exc)


    # -- event loop side ------------------------------------------------------------------------
    def _on_datagram(self, data: bytes, addr: Addr) -> None:
        """Event loop: count the datagram and gather it into the batch being formed.

        The batch goes to the decoder in one queue put, ``batch_wait_s`` after its first
        datagram or as soon as it holds ``batch_max`` (:meth:`_hand_over`): the decoder thread
        wakes once per batch, not once per datagram. ``queue_max`` bounds the datagrams accepted
        and not yet taken by the decoder (gathering or queued).
        """
        m = self.metrics
        m.received += 1
        m.received_bytes += len(data)
        if self._stopping:  # arrived after shutdown began: not acked, so the sender retries
            m.drop("shutdown")
            return
        if self._accepted_in - self._taken_out >= self.config.queue_max:
            m.drop("queue_full")
            return
        g = self._gathering
        g.append((data, addr, self._clock()))
        self._accepted_in += 1
        if len(g) >= self.config.batch_max or self._loop is None:
            self._hand_over()
        elif self._hand_over_at is None:
            self._hand_over_at = self._loop.call_later(self.config.batch_wait_s,
                                                       self._hand_over)

    def _hand_over(self) -> None:
        """Event loop: the gathered datagrams to the decoder, as one batch."""
        if self._hand_over_at is not None:
            self._hand_over_at.cancel()
            self._hand_over_at = None
        if self._gathering:
            batch, self._gathering = self._gathering, []
            self._queue.put_nowait(batch)

    def _queue_depth(self) -> int:
        """Datagrams accepted and not yet taken by the decoder."""
        return max(0, self._accepted_in - self._taken_out)

    # -- protocol (the only place that knows the Receiver's API) --------------------------------
    def _rx_receive(self, data: bytes, now: int) -> Item:
        with self._rx_lock:
            return self._receiver.receive(data, now)

    def _rx_mark_durable(self, item: Item) -> None:
        self._receiver.mark_durable(item.machine_id, item.epoch, item.seq)

    def _rx_ack(self, machine_id: str, epoch: int, now: int) -> bytes:
        return self._receiver.ack(machine_id, epoch, now)

    def _rx_refusal(self, machine_id: str, epoch: int, seq: int, reason: str, now: int) -> bytes:
        return self._receiver.refuse(machine_id, epoch, seq, reason, now)

    def _decode(self, raw: list[Raw]) -> list[tuple[Item, Addr]]:
        """Decoder thread: authenticate and decode; bad datagrams are counted and dropped.

        Only an authenticated datagram is ever answered, and only in two ways: a replay of a
        durable one with an ack for its epoch (one per machine, epoch and address and batch: its
        earlier ack was probably lost), a refused one (out of range, bad time, oversize, bad
        seq) with its refusal. Anything else — forged, unknown machine, garbage, bad layout —
        gets nothing, whatever its header claims.
        """
        m = self.metrics
        items: list[tuple[Item, Addr]] = []
        reack: dict[tuple[str, int, Addr], None] = {}
        replies: list[tuple[bytes, Addr]] = []
        for data, addr, now in raw:
            try:
                items.append((self._rx_receive(data, now), addr))
            except ReplayedError as exc:
                m.drop(exc.reason)
                if exc.authenticated and exc.machine_id is not None:
                    reack[(exc.machine_id, exc.epoch, addr)] = None
            except RefusedError as exc:
                m.drop(exc.reason)
                if exc.authenticated:
                    with contextlib.suppress(KeyError, ValueError), self._rx_lock:
                        replies.append((self._receiver.refusal(exc, now), addr))
            except DatagramError as exc:
                reason = exc.reason
                if reason == "unknown_machine" and exc.wire_id in self.keys.bad_models:
                    reason = "bad_model"
                m.drop(reason)
            except Exception as exc:  # a bug must not stop ingest: count, log once, go on
                m.drop("internal_error")
                self._log_once("decode", exc, "unexpected error decoding a datagram "
                               "(counted as internal_error, dropped): %s", exc)
        now_ns = self._clock()
        for machine_id, epoch, addr in reack:
            with contextlib.suppress(KeyError), self._rx_lock:
                replies.append((self._rx_ack(machine_id, epoch, now_ns), addr))
        for data, addr in replies:
            self._sendto(data, addr, "refusals_sent" if _is_refusal(data) else "acks_sent")
        m.add("accepted", len(items))
        return items

    def _sendto(self, data: bytes, addr: Addr, counter: str) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(data, addr)
            self.metrics.add(counter)
        except OSError:  # full buffer or unreachable: the sender retransmits and is acked then
            self.metrics.drop("ack_send_error")
    # -- acks after commit ----------------------------------------------------------------------
    def _after_commit(self, durable: list[tuple[Item, Addr]],
                      refused: list[tuple[Item, Addr, str]]) -> None:
        """Writer thread, after commit: mark durable, then one ack per (machine, epoch,
        address); one refusal per refused block."""
        dest: dict[tuple[str, int, Addr], None] = {}
        out: list[tuple[bytes, Addr, str]] = []
        now = self._clock()
        with self._rx_lock:
            for item, addr in durable:
                self._rx_mark_durable(item)
                dest[(item.machine_id, item.epoch, addr)] = None
            for machine_id, epoch, addr in dest:
                with contextlib.suppress(KeyError):
                    out.append((self._rx_ack(machine_id, epoch, now), addr, "acks_sent"))
            for item, addr, reason in refused:
                self.metrics.drop(reason)
                reply: bytes | None = None
                wire_reason = reason if reason in REFUSAL_CODES else "unstorable"
                with contextlib.suppress(KeyError, ValueError):
                    reply = self._rx_refusal(item.machine_id, item.epoch, item.seq, wire_reason,
                                             now)
                if reply is not None:  # (a version-1 sender gets an ack: it has no refusals)
                    out.append((reply, addr,
                                "refusals_sent" if _is_refusal(reply) else "acks_sent"))
        for data, addr, counter in out:
            self._sendto(data, addr, counter)
