"""A bounded pool for heavy work, apart from the threads that serve cheap requests.

A twin replay (numba kernels and tens of MB of arrays), an analytics range, a report or an export
takes 0.1 s to minutes; a machine list or a history query a few ms. Run on the same thread pool,
24 concurrent replays of one client took every thread and ~1 GB, and another client's cheap
requests queued behind them. So heavy work runs here: ``workers`` threads of its own and at most
``queue`` jobs waiting for one; a job beyond that is refused at once with :class:`BusyError`
(HTTP 503 with ``Retry-After``), never queued without bound. Memory of heavy work in flight is so
bounded by ``workers`` replays.

A streamed result (an export produced chunk by chunk while it is sent) takes one admission for
the whole stream (:meth:`HeavyPool.lease`) and runs each chunk on the pool's threads. Twin
replays may instead run in worker processes (``heavy_processes``;
:mod:`cranetwin.service.heavyproc`), under the same admission. The processes start in the
background (:meth:`HeavyPool.start_processes`: at the API's start when it warms up, else at
the first replay), so that starting them (2–3 s of CPU, seconds more on a busy host) never
delays serving; until every one has started and warmed up, replays run on the heavy threads.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any, TypeVar

from cranetwin.service.errors import BusyError

T = TypeVar("T")
log = logging.getLogger(__name__)


class Lease:
    """One admission into a :class:`HeavyPool`, for a sequence of calls (a stream); release it
    (or use it as a context manager) when done. At most one call of a lease is outstanding."""

    def __init__(self, pool: HeavyPool) -> None:
        self._pool = pool
        self._released = False

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """Run ``fn(*args)`` on a heavy thread (no further admission)."""
        return self._pool._executor.submit(fn, *args)

    def release(self) -> None:
        """Give the admission back (idempotent)."""
        if not self._released:
            self._released = True
            self._pool._release()

    def __enter__(self) -> Lease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class HeavyPool:
    """``workers`` threads for heavy work, at most ``queue`` jobs waiting (see module docstring).

    Args:
        workers: Threads running heavy work.
        queue: Jobs admitted beyond the running ones; more are refused.
        retry_after_s: The ``retry_after_s`` of a refusal [s].
        processes: Worker processes for the calls that name a ``process_fn`` (not started
            yet: a ``ProcessPoolExecutor`` starts its processes at its first call), or None.
        process_count: How many processes ``processes`` has.
        process_warm: A module-level function each process runs once when started
            (:meth:`start_processes`; loads compiled kernels).
    """

    def __init__(self, workers: int, queue: int, retry_after_s: float = 1.0,
                 processes: Executor | None = None, process_count: int = 1,
                 process_warm: Callable[[], object] = int) -> None:
        if workers < 1 or queue < 0:
            raise ValueError(f"workers={workers} (≥ 1), queue={queue} (≥ 0)")
        self.workers = workers
        self.limit = workers + queue
        self.retry_after_s = retry_after_s
        self.refused = 0
        self.processes = processes
        self.process_count = process_count
        self._process_warm = process_warm
        self._processes_ready = threading.Event()
        self._processes_started = False
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="cranetwin-heavy")
        self._lock = threading.Lock()
        self._admitted = 0

    @property
    def processes_ready(self) -> bool:
        """Whether the worker processes have started and warmed up (calls go to them)."""
        return self._processes_ready.is_set()

    def start_processes(self) -> None:
        """Start the worker processes in the background, each warming up once; calls with a
        ``process_fn`` go to them when all have. Returns at once; idempotent. A process that
        fails to start is logged and leaves the calls on the threads."""
        with self._lock:
            if self.processes is None or self._processes_started:
                return
            self._processes_started = True
        t0 = time.monotonic()
        left = [self.process_count]
        failed: list[BaseException] = []

        def done(fut: Future[object]) -> None:
            exc = RuntimeError("cancelled") if fut.cancelled() else fut.exception()
            with self._lock:
                left[0] -= 1
                if exc is not None:
                    failed.append(exc)
                last = left[0] == 0
            if last and not failed:
                self._processes_ready.set()
                log.info("replay worker processes ready after %.1f s", time.monotonic() - t0)
            elif last:
                log.warning("replay worker processes did not start (%s): replays stay on the "
                            "heavy threads", failed[0])

        try:
            futures = [self.processes.submit(self._process_warm)
                       for _ in range(self.process_count)]
        except RuntimeError as exc:  # shut down meanwhile
            log.warning("replay worker processes not started: %s", exc)
            return
        for fut in futures:
            fut.add_done_callback(done)

    @property
    def admitted(self) -> int:
        """Jobs (and leases) admitted and not finished: running plus waiting."""
        return self._admitted

    def _admit(self) -> None:
        with self._lock:
            if self._admitted >= self.limit:
                self.refused += 1
                raise BusyError("Server busy", f"{self._admitted} heavy requests (replays, "
                                "reports, exports) are running or waiting, the most this server "
                                "takes; retry in a moment", self.retry_after_s)
            self._admitted += 1

    def _release(self) -> None:
        with self._lock:
            self._admitted -= 1

    def submit(self, fn: Callable[..., T], *args: Any,
               process_fn: Callable[..., T] | None = None) -> Future[T]:
        """Run ``fn(*args)`` on a heavy thread, or ``process_fn(*args)`` (a module-level
        function: it and the arguments are pickled) in a worker process when the pool has them
        and they are ready (the first such call starts them: :meth:`start_processes`).

        Raises:
            BusyError: ``workers + queue`` jobs are admitted already.
        """
        self._admit()
        try:
            if process_fn is not None and self.processes is not None \
                    and not self._processes_ready.is_set():
                self.start_processes()
            if process_fn is not None and self.processes is not None \
                    and self._processes_ready.is_set():
                fut = self.processes.submit(process_fn, *args)
            else:
                fut = self._executor.submit(fn, *args)
        except BaseException:
            self._release()
            raise
        fut.add_done_callback(lambda _: self._release())
        return fut

    def lease(self) -> Lease:
        """One admission for a sequence of calls (:class:`Lease`).

        Raises:
            BusyError: As :meth:`submit`.
        """
        self._admit()
        return Lease(self)

    def close(self) -> None:
        """Stop the threads after the running jobs (waiting jobs are cancelled), and the worker
        processes after theirs (without waiting: a process still starting finishes its start
        and exits; the interpreter waits for them at its exit)."""
        self._executor.shutdown(wait=False, cancel_futures=True)
        if self.processes is not None:
            self.processes.shutdown(wait=False, cancel_futures=True)
