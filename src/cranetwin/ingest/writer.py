"""The ingest daemon's database side: batch writes retried with backoff while storage is
unavailable, written again block by block after a failure storage did not explain, status
reports, and the periodic 1-min rollup.

Used by the daemon's writer thread; the supervisor reads :attr:`StorageWriter.outage` and
:attr:`StorageWriter.progress`, and shutdown sets :attr:`StorageWriter.abandon`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any, Literal

from cranetwin.ingest.config import DaemonConfig
from cranetwin.ingest.metrics import Metrics
from cranetwin.protocol.status import StatusReport
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store, WriteResult, dberrors

log = logging.getLogger("cranetwin.ingest.daemon")  # one logger for the daemon's messages

Outcome = tuple[Literal["stored", "duplicate", "refused", "error"], str]
"""Per-block result of a write: stored (new), duplicate (already held), refused (never storable,
with storage's refusal reason) or error (the block could not be written even alone, for a reason
storage did not explain: neither acked nor refused, so its sender retransmits; counted as
``write_error``)."""


def outcomes_of(result: WriteResult) -> list[Outcome]:
    """Storage's outcomes as the daemon's; ``unavailable`` (the machine's shard failed while
    the others were written) is an ``error``: neither acked nor refused, retransmitted."""
    out: list[Outcome] = []
    for o in result.outcomes:
        if o.status == "refused":
            out.append(("refused", o.reason or "unstorable"))
        elif o.status == "unavailable":
            out.append(("error", o.reason or "shard_unavailable"))
        else:
            out.append((o.status, ""))
    return out


def is_unavailable(exc: BaseException) -> bool:
    """Whether ``exc`` is an operational database failure (connection lost, server down,
    database locked, disk I/O): the write should be retried, not refused
    (:func:`cranetwin.storage.dberrors.unavailable_in_chain`)."""
    return dberrors.unavailable_in_chain(exc)


class Abandoned(Exception):
    """Shutdown gave up retrying (storage unavailable)."""


class StorageWriter:
    """Writes to the daemon's :class:`~cranetwin.storage.Store` (see the module docstring).

    Args:
        store: Where blocks and status reports go.
        config: The daemon's settings (retry backoff, rollup interval).
        metrics: The daemon's counters.
        log_once: The daemon's log-once function ``(kind, exc, msg, *args)``.

    Attributes:
        outage: True from the first failed attempt of an outage until a write succeeds.
        progress: Last time the writer was not inside a database call [monotonic s].
        idle: True while the writer thread waits for a batch (not in a database call, however
            old ``progress`` is).
        abandon: Set at shutdown to give up retrying (raises :class:`Abandoned`).
    """

    def __init__(self, store: Store, config: DaemonConfig, metrics: Metrics,
                 log_once: Callable[..., None]) -> None:
        self.store = store
        self.config = config
        self.metrics = metrics
        self._log_once = log_once
        self.outage = False
        self.progress = time.monotonic()
        self.idle = False
        self.abandon = threading.Event()
        self._outage_since: float | None = None
        self._last_rollup = time.monotonic()

    def retry(self, what: str, fn: Callable[[], Any]) -> Any:
        """``fn()``, retried with exponential backoff while storage is unavailable.

        Raises:
            Abandoned: shutdown gave up while storage was unavailable.
            Exception: whatever ``fn`` raised that is not unavailability.
        """
        cfg = self.config
        delay = cfg.retry_min_s
        while True:
            try:
                result = fn()
            except Exception as exc:
                self.progress = time.monotonic()
                if not is_unavailable(exc):
                    raise
                self.metrics.add("write_errors")
                if self._outage_since is None:
                    self._outage_since = time.monotonic()
                    self.outage = True
                    log.error("storage unavailable (%s): retrying with backoff up to %.1f s, "
                              "nothing is acknowledged meanwhile: %s", what, cfg.retry_max_s,
                              " ".join(str(exc).split())[:500])
                if self.abandon.wait(delay):
                    raise Abandoned() from exc
                delay = min(2 * delay, cfg.retry_max_s)
                continue
            self.progress = time.monotonic()
            if self._outage_since is not None:
                log.warning("storage available again after %.1f s; ingest resumes",
                            time.monotonic() - self._outage_since)
                self._outage_since = None
                self.outage = False
            return result

    def write_blocks(self, blocks: Sequence[SampleBlock]) -> list[Outcome]:
        """Per-block outcomes of one :meth:`Store.write_batch`, retried while storage is
        unavailable. A batch that fails as a whole for another reason (nothing of it stored)
        is written again block by block, so such a failure only ever holds back the blocks
        that cause it."""
        if not blocks:
            return []
        try:
            result: WriteResult = self.retry("batch", partial(self.store.write_batch, blocks))
            return outcomes_of(result)
        except Abandoned:
            raise
        except Exception as exc:
            self.metrics.add("write_errors")
            self._log_once("write_batch", exc, "batch write failed unexpectedly, writing its "
                           "%d block(s) one by one: %s", len(blocks), exc)
        outcomes: list[Outcome] = []
        for b in blocks:
            try:
                one: WriteResult = self.retry("block", partial(self.store.write_batch, [b]))
                outcomes.extend(outcomes_of(one))
            except Abandoned:
                raise
            except Exception as exc:
                self.metrics.add("write_errors")
                self._log_once("write_block", exc, "a block of %s (epoch %d, seq %d) could not "
                               "be written alone (not acknowledged; its sender retransmits): %s",
                               b.machine_id, b.epoch, b.seq, exc)
                outcomes.append(("error", "write_error"))
        return outcomes

    def write_status(self, r: StatusReport) -> None:
        def val(x: float) -> float | None:
            return None if x != x else x  # NaN → not reported

        self.store.update_status(r.machine_id, r.t_ns / 1e9, latitude_deg=val(r.latitude_deg),
                                 longitude_deg=val(r.longitude_deg),
                                 altitude_m=val(r.altitude_m),
                                 operating_hours=val(r.operating_hours))
        self.metrics.add("status_reports")

    def rollup_due_in(self) -> float:
        """Time until :meth:`maybe_rollup` next rolls up [s] (0 when due)."""
        return max(0.0, self._last_rollup + self.config.rollup_interval_s - time.monotonic())

    def maybe_rollup(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_rollup < self.config.rollup_interval_s:
            return
        self._last_rollup = now
        try:
            # minutes that ended a while ago (machine clocks may lag), or everything at shutdown
            self.store.rollup(None if force else time.time() - 120)
        except Exception as exc:  # never fatal: dirty minutes stay exact, retried next time
            self.metrics.add("rollup_errors")
            self._log_once("rollup", exc, "summary rollup failed (queries stay exact; retried "
                           "every %.0f s): %s", self.config.rollup_interval_s, exc)
        finally:
            self.progress = time.monotonic()
