"""The ingest daemon's JetStream sink: a :class:`~cranetwin.storage.Store` whose block writes go
to the fleet bus instead of the database.

:class:`JetStreamStore` is the database's :class:`~cranetwin.storage.Store` (machine keys and
status reports are read and written there as before) with two methods replaced:

* :meth:`JetStreamStore.write_batch` publishes every block to JetStream
  (:mod:`cranetwin.bus.subjects`) and returns once every PubAck is in: ``stored`` for a new
  message, ``duplicate`` when JetStream reports the message id as already seen, ``refused``
  (``unstorable``) for a block storage would refuse whatever happens (checked here with
  storage's own :func:`~cranetwin.storage.blocks.check_block`, before publishing). When the bus
  does not answer, the whole call raises
  :class:`~cranetwin.errors.StorageUnavailableError`: the daemon retries the batch with backoff
  and acknowledges nothing meanwhile; blocks of the batch that did reach the stream come back
  as ``duplicate`` on the retry.
* :meth:`JetStreamStore.rollup` does nothing: the storage writers roll up what they store.

So the daemon, unchanged, acknowledges a machine once its blocks are in the stream (file
storage). What becomes of them next is :mod:`cranetwin.bus.consumer`'s part.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from typing import Any

import orjson

from cranetwin.bus.blockcodec import encode_blocks
from cranetwin.bus.subjects import BusConfig, ensure_stream, msg_id_of, subject_of
from cranetwin.errors import StorageUnavailableError
from cranetwin.samples import SampleBlock
from cranetwin.storage import ShardedStore, Store, StoreSpec
from cranetwin.storage import blocks as blocks_mod
from cranetwin.storage.engine import BUSY_TIMEOUT_S, DEFAULT_URL, make_engine, migrate
from cranetwin.storage.nats_loop import NatsLoop
from cranetwin.storage.writes import DUPLICATE, STORED, BlockOutcome, WriteResult, refused

log = logging.getLogger(__name__)


class JetStreamPublisher:
    """Publishes block messages to the fleet bus and waits for their PubAcks.

    Each message is a plain NATS publish with a reply subject under one inbox of this
    publisher (the PubAck comes back there), so a batch of messages is in flight at once and
    costs one round trip; nats-py's ``publish_async`` does the same with about twice the CPU
    per message.

    Args:
        cfg: The bus settings.
        name: Client name shown by the NATS server.
    """

    def __init__(self, cfg: BusConfig, name: str = "cranetwin-ingest") -> None:
        self.cfg = cfg
        self.conn = NatsLoop(cfg.url, name=name, connect_timeout_s=cfg.publish_timeout_s)
        self._nc: Any = None
        self._stream_ok = False
        self._prefix = ""
        self._futs: dict[str, asyncio.Future[bytes]] = {}
        self._next = 0
        self._max_payload = 1 << 20

    async def _on_reply(self, msg: Any) -> None:
        fut = self._futs.pop(msg.subject[len(self._prefix):], None)
        if fut is None or fut.done():
            return
        status = msg.headers.get("Status") if msg.headers else None
        if status is not None and not msg.data:  # 503: no stream takes the subject
            fut.set_exception(StorageUnavailableError(f"JetStream answered status {status} "
                                                      "(no stream for the subject)"))
        else:
            fut.set_result(msg.data)

    async def _setup(self, nc: Any) -> None:
        if self._nc is not nc:  # one reply subscription per connection (kept on reconnects)
            self._prefix = nc.new_inbox() + "."
            await nc.subscribe(self._prefix + "*", cb=self._on_reply)
            self._nc = nc
        if not self._stream_ok:
            await ensure_stream(nc.jetstream(timeout=self.cfg.publish_timeout_s), self.cfg)
            self._max_payload = int(nc.max_payload or self._max_payload)
            self._stream_ok = True

    def publish(self, items: Sequence[tuple[str, str, bytes]]) -> list[bool]:
        """Publish ``(subject, message id, body)`` items; returns once every PubAck is in.

        Returns:
            Per item, whether JetStream reported it as a duplicate (already in the stream
            within the duplicate window).

        Raises:
            StorageUnavailableError: NATS or JetStream did not acknowledge every item within
                ``publish_timeout_s``, or refused one (stream full, …); some may be in the
                stream: publishing them again is safe.
        """
        if not items:
            return []

        async def pub(nc: Any) -> list[bool]:
            await self._setup(nc)
            loop = asyncio.get_running_loop()
            toks: list[str] = []
            futs: list[asyncio.Future[bytes]] = []
            try:
                for subject, mid, body in items:
                    self._next += 1
                    tok = str(self._next)
                    fut: asyncio.Future[bytes] = loop.create_future()
                    self._futs[tok] = fut
                    toks.append(tok)
                    futs.append(fut)
                    await nc.publish(subject, body, reply=self._prefix + tok,
                                     headers={"Nats-Msg-Id": mid})
                replies = await asyncio.wait_for(asyncio.gather(*futs),
                                                 self.cfg.publish_timeout_s)
            finally:
                for tok in toks:
                    self._futs.pop(tok, None)
                for f in futs:
                    f.cancel()
            dups: list[bool] = []
            for data in replies:
                ack = orjson.loads(data)
                if "error" in ack:
                    raise StorageUnavailableError(f"JetStream refused a block: {ack['error']}")
                dups.append(bool(ack.get("duplicate")))
            return dups

        try:
            return self.conn.run(pub, self.cfg.publish_timeout_s + 1.0)
        except StorageUnavailableError:
            self._stream_ok = False  # the server may have restarted without the stream
            raise
        except Exception as exc:  # a JetStream API error: nothing to do but retry later
            self._stream_ok = False
            raise StorageUnavailableError(f"JetStream refused the batch: {type(exc).__name__}: "
                                          f"{exc}") from exc

    @property
    def max_payload(self) -> int:
        """Largest message the server accepts [bytes] (known after the first publish)."""
        return self._max_payload

    def close(self) -> None:
        self.conn.close()


class JetStreamStore(Store):
    """The database :class:`Store` with block writes going to the fleet bus (module docstring).

    Create it with :meth:`open_bus`.
    """

    publisher: JetStreamPublisher

    @classmethod
    def open_bus(cls, url: str | StoreSpec = DEFAULT_URL, bus: BusConfig | None = None, *,
                 busy_timeout_s: float = BUSY_TIMEOUT_S) -> JetStreamStore:
        """Connect to the database at ``url`` (machines, status; a
        :class:`~cranetwin.storage.StoreSpec` with shards: every shard) and to the bus ``bus``.

        Raises:
            StorageUnavailableError: The database server is unreachable.
            StorageError: Bad URL or failed migration.
            MissingExtraError: nats-py is not installed.
        """
        spec = StoreSpec(url) if isinstance(url, str) else url
        shard_map = spec.shard_map()
        store: JetStreamStore
        if shard_map is not None:
            sharded = ShardedStore.open_map(shard_map, busy_timeout_s=busy_timeout_s)
            store = ShardedJetStreamStore(sharded.shards, shard_map, sharded.ready)
        else:
            store = cls(make_engine(spec.url, busy_timeout_s=busy_timeout_s))
            migrate(store.engine)
        store.publisher = JetStreamPublisher(bus or BusConfig())
        return store

    def write_batch(self, blocks: Sequence[SampleBlock]) -> WriteResult:
        """Publish ``blocks`` to the bus (see the module docstring).

        Raises:
            StorageUnavailableError: The bus did not acknowledge the batch.
        """
        blocks = list(blocks)
        outcomes: list[BlockOutcome | None] = [None] * len(blocks)
        ok: list[int] = []
        for i, b in enumerate(blocks):
            why = blocks_mod.check_block(b)
            if why is not None:
                outcomes[i] = refused("unstorable", why)
            else:
                ok.append(i)
        bodies = encode_blocks([blocks[i] for i in ok], self.publisher.cfg.level)
        cfg = self.publisher.cfg
        items: list[tuple[str, str, bytes]] = []
        where: list[int] = []
        for i, body in zip(ok, bodies, strict=True):
            if isinstance(body, str):
                outcomes[i] = refused("unstorable", body)
            elif len(body) > self.publisher.max_payload - 1024:
                outcomes[i] = refused("unstorable", f"block of {len(body)} bytes exceeds the "
                                      f"bus's largest message ({self.publisher.max_payload})")
            else:
                b = blocks[i]
                items.append((subject_of(cfg, b.machine_id),
                              msg_id_of(b.machine_id, int(b.epoch), int(b.seq)), body))
                where.append(i)
        for i, dup in zip(where, self.publisher.publish(items), strict=True):
            outcomes[i] = DUPLICATE if dup else STORED
        return WriteResult(tuple(blocks), tuple(o if o is not None else refused(
            "unstorable", "internal error: undecided") for o in outcomes))

    def rollup(self, before_s: float | None = None) -> int:
        """Nothing to roll up here: the storage writers roll up the minutes they store."""
        return 0

    def close(self) -> None:
        self.publisher.close()
        super().close()


class ShardedJetStreamStore(JetStreamStore, ShardedStore):
    """:class:`JetStreamStore` whose machines and status reports live on the shards of a
    :class:`~cranetwin.storage.shards.ShardedStore` (blocks still go to the bus)."""
