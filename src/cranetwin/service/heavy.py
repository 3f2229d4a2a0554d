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
:mod:`cranetwin.service.heavyproc`), under the same admission.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any, TypeVar

from cranetwin.service.errors import BusyError

T = TypeVar("T")


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
    """

    def __init__(self, workers: int, queue: int, retry_after_s: float = 1.0,
                 processes: Executor | None = None) -> None:
        if workers < 1 or queue < 0:
            raise ValueError(f"workers={workers} (≥ 1), queue={queue} (≥ 0)")
        self.workers = workers
        self.limit = workers + queue
        self.retry_after_s = retry_after_s
        self.refused = 0
        self.processes = processes
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="cranetwin-heavy")
        self._lock = threading.Lock()
        self._admitted = 0

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
        function: it and the arguments are pickled) in a worker process when the pool has them.

        Raises:
            BusyError: ``workers + queue`` jobs are admitted already.
        """
        self._admit()
        try:
            if process_fn is not None and self.processes is not None:
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
        processes (waiting for them to exit)."""
        self._executor.shutdown(wait=False, cancel_futures=True)
        if self.processes is not None:
            self.processes.shutdown(wait=True, cancel_futures=True)
