"""Live fan-out over core NATS: :class:`NatsBus` (``nats://host:port`` in
:func:`cranetwin.storage.live.open_bus`).

The same notes as the Redis and PostgreSQL transports (JSON arrays of
:class:`~cranetwin.storage.live.BlockNote`, no samples: the subscriber reads those from storage)
on one core NATS subject, ``cranetwin.live`` by default. Core NATS keeps nothing: a subscriber
gets what is published while it is subscribed, which is what a live view needs (the durable
path is the JetStream fleet bus, :mod:`cranetwin.bus`). A slow subscriber never slows the
publisher: nats-py buffers per subscription and this bus's queue drops the oldest notes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cranetwin.samples import SampleBlock
from cranetwin.storage.live import Subscription, _notes, _payloads, _QueueSubscription
from cranetwin.storage.nats_loop import NatsLoop

SUBJECT = "cranetwin.live"
_TIMEOUT_S = 2.0


class NatsBus:
    """Core NATS ``PUBLISH``/``SUBSCRIBE`` (daemon or store-writer and API in separate processes).

    Args:
        url: ``nats://host:port``.
        subject: Subject of the notes.
        maxsize: Notes buffered per subscriber before the oldest are dropped.

    Raises:
        MissingExtraError: nats-py is not installed (``cranetwin[nats]``).
    """

    def __init__(self, url: str = "nats://127.0.0.1:4222", subject: str = SUBJECT,
                 maxsize: int = 10_000) -> None:
        self._conn = NatsLoop(url, name="cranetwin-live")
        self._subject = subject
        self._maxsize = maxsize
        self._subs: list[Any] = []

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        """Publish notes of ``blocks`` and flush them to the server.

        Raises:
            StorageUnavailableError: NATS cannot be reached.
        """
        payloads = [p.encode() for p in _payloads(blocks, limit=64_000)]

        async def pub(nc: Any) -> None:
            for p in payloads:
                await nc.publish(self._subject, p)
            await nc.flush(timeout=_TIMEOUT_S)

        self._conn.run(pub, _TIMEOUT_S)

    def subscribe(self) -> Subscription:
        """A subscription that receives every note published after this call returns (the
        server has registered it: the call flushes).

        Raises:
            StorageUnavailableError: NATS cannot be reached.
        """
        queue_sub = _QueueSubscription(self._maxsize)

        async def on_msg(msg: Any) -> None:
            for note in _notes(msg.data):
                queue_sub.put(note)

        async def sub(nc: Any) -> Any:
            s = await nc.subscribe(self._subject, cb=on_msg)
            await nc.flush(timeout=_TIMEOUT_S)
            return s

        nats_sub = self._conn.run(sub, _TIMEOUT_S)
        self._subs.append(nats_sub)

        def close(_: _QueueSubscription) -> None:
            if nats_sub in self._subs:
                self._subs.remove(nats_sub)

                async def unsub(_nc: Any) -> None:
                    await nats_sub.unsubscribe()

                try:
                    self._conn.run(unsub, _TIMEOUT_S)
                except Exception:  # the connection is gone: so is the subscription
                    pass

        queue_sub._on_close = close
        return queue_sub

    def close(self) -> None:
        """Unsubscribe everything and close the connection."""
        self._subs.clear()
        self._conn.close()
