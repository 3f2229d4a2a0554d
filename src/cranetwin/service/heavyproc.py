"""The twin replays of the API in processes of their own (setting ``heavy_processes``).

A replay in a thread of the API process shares its interpreter: the replay's Python and
serialisation hold the interpreter lock for milliseconds at a time, and every cheap request
waits for it at each database read (measured: a machine list 2.7× slower while one key's
replays ran on two threads, 7× while that key also sent hundreds of refused requests). A
process of its own has its own interpreter, so the API's cheap requests wait for nothing but
the CPU. Each worker process opens its own store and replayer (:func:`init_worker`, started by
``concurrent.futures.ProcessPoolExecutor`` with the ``spawn`` method: no inherited threads or
connections) and returns the replay as JSON bytes, which the API process caches.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

from cranetwin.service.backend import MachineRecord
from cranetwin.service.fleet import FleetService
from cranetwin.service.timerange import TimeRange
from cranetwin.settings import Settings

_FLEET: FleetService | None = None
"""The worker process's fleet service (set by :func:`init_worker`)."""


def init_worker(settings: Settings) -> None:
    """Open the store and the replayer of a worker process."""
    global _FLEET
    _FLEET = FleetService.open(settings)


def warm() -> int:
    """Load the replay's compiled kernels in a worker process (the warm-up of the API, then the
    newest 30 s of the most recently seen machines); returns the machines replayed."""
    from cranetwin.service.warmup import run_warm_up

    assert _FLEET is not None, "init_worker was not run"
    run_warm_up(then=_FLEET.warm_machines)
    return 0


def twin_body(rec: MachineRecord, rng: TimeRange, rate_hz: float) -> bytes:
    """:meth:`FleetService.twin_body` in a worker process."""
    assert _FLEET is not None, "init_worker was not run"
    return _FLEET.twin_body(rec, rng, rate_hz)


def process_pool(settings: Settings) -> ProcessPoolExecutor:
    """``settings.replay_processes`` worker processes for twin replays (started at the first
    call)."""
    return ProcessPoolExecutor(settings.replay_processes,
                               mp_context=multiprocessing.get_context("spawn"),
                               initializer=init_worker, initargs=(settings,))
