"""The fleet bus on NATS JetStream (docs/BUS.md): ingest daemons publish decoded blocks
(:class:`~cranetwin.bus.sink.JetStreamStore`), storage writers consume them into the database
(:class:`~cranetwin.bus.consumer.StoreWriter`), one message per block, partitioned by machine,
deduplicated by (machine, epoch, seq).

nats-py is the ``nats`` extra; the modules import it lazily and raise
:class:`~cranetwin.errors.MissingExtraError` without it.
"""

from __future__ import annotations

from cranetwin.bus.subjects import BusConfig, msg_id_of, subject_of
from cranetwin.storage.sharding import partition_of

__all__ = ["BusConfig", "msg_id_of", "partition_of", "subject_of"]
