"""The service layer: what the fleet's stored data become, with no HTTP in it.

Below the HTTP API (:mod:`cranetwin.api`, which only parses requests, calls one function here and
turns the result into a response) and above twin, analytics and storage:

* :mod:`~cranetwin.service.fleet` — :class:`FleetService`: machine status, samples paging, twin
  windows (cached), history from summaries, "find the moment", events, analytics and reports,
  ISO 15143-3 snapshots; plain data out, :mod:`~cranetwin.service.errors` raised.
* :mod:`~cranetwin.service.queries` — samples paging and "find the moment" (no replay).
* :mod:`~cranetwin.service.backend` — the adapter over storage (machines, samples, summaries,
  events, keys, twin progress).
* :mod:`~cranetwin.service.worker` — :class:`TwinWorker`, run as ``cranetwin worker`` (or inside
  ``cranetwin serve`` for the demo): stored samples → derived summaries, events, counters.
* :mod:`~cranetwin.service.replayer` — replays reusing each machine's smoothing choice; the
  sample period from the data.
* :mod:`~cranetwin.service.analytics` — a range replayed into :mod:`cranetwin.analytics`.
* :mod:`~cranetwin.service.aemp` — ISO 15143-3 (AEMP 2.0) snapshots.
* :mod:`~cranetwin.service.live_payload` — the live view's payload estimate.
* :mod:`~cranetwin.service.views` — twin results and live samples as the public JSON shapes.
* :mod:`~cranetwin.service.timerange`, :mod:`~cranetwin.service.keys`,
  :mod:`~cranetwin.service.cache`, :mod:`~cranetwin.service.metrics`,
  :mod:`~cranetwin.service.warmup` — time ranges, stored API keys, the replay cache, Prometheus
  counters, warm-up after start.

A test imports every module here in a fresh interpreter and asserts that neither fastapi nor
starlette was loaded.
"""

from __future__ import annotations

from cranetwin.service.backend import Backend, MachineRecord, Progress
from cranetwin.service.errors import (
    ConflictError,
    InvalidRequestError,
    NotFoundError,
    ServiceError,
)
from cranetwin.service.fleet import FleetService
from cranetwin.service.worker import TwinWorker

__all__ = ["Backend", "ConflictError", "FleetService", "InvalidRequestError", "MachineRecord",
           "NotFoundError", "Progress", "ServiceError", "TwinWorker"]
