"""Payload estimate for the live stream, fresher than the twin worker's per-minute one.

The twin worker stores the payload of a window once the whole window (60 s) is stored, so its
latest estimate is up to about a minute old, and it does not exist before the first window. A
:class:`LivePayload` replays the newest ``span_s`` of stored samples of one machine (the twin's
sliding-window least-squares estimate, :mod:`cranetwin.twin`) at most every ``every_s`` in a
background thread and keeps the median estimate of the last second that is at least
``margin_s`` before the newest sample (away from the spline's end). Until it has one, or when
the replay fails, the worker's latest estimate is used. Reading the value never blocks.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from cranetwin.errors import CraneTwinError
from cranetwin.model import Machine

if TYPE_CHECKING:
    from cranetwin.service.backend import Backend
    from cranetwin.service.replayer import Replayer

log = logging.getLogger(__name__)


def public_kg(kg: float | None) -> float | None:
    """A payload estimate as shown to clients: None when unknown (None/NaN), else rounded to
    0.1 kg and at least 0 (a small negative estimate is noise around an empty grapple) [kg]."""
    if kg is None or not math.isfinite(kg):
        return None
    return round(max(0.0, float(kg)), 1)


class LivePayload:
    """Latest payload estimate of one machine (see module docstring).

    Args:
        machine_id: Machine identifier.
        machine: Its description.
        backend: Store adapter (samples, worker progress).
        replayer: Shared replayer (reuses the machine's smoothing choice).
        span_s: Newest stored samples replayed per refresh [s].
        every_s: Least time between refreshes [s].
        margin_s: Estimates this close to the newest sample are not used [s].
        clock: Monotonic clock [s] (injectable for tests).
    """

    def __init__(self, machine_id: str, machine: Machine, backend: Backend, replayer: Replayer,
                 span_s: float = 20.0, every_s: float = 2.0, margin_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.machine_id = machine_id
        self.machine = machine
        self.backend = backend
        self.replayer = replayer
        self.span_s = span_s
        self.every_s = every_s
        self.margin_s = margin_s
        self.clock = clock
        self.kg: float | None = None
        """Newest live estimate [kg] (None before the first successful refresh)."""
        self.t_s: float | None = None
        """Sample time of that estimate [s since the epoch]."""
        self._last = -math.inf
        self._end: float | None = None  # newest stored time [s] the estimate was made from
        self._busy = threading.Lock()
        self._thread: threading.Thread | None = None

    def value(self) -> float | None:
        """Latest estimate [kg]: the live one, else the twin worker's; starts a refresh in the
        background when one is due. Never blocks."""
        now = self.clock()
        if now - self._last >= self.every_s and self._busy.acquire(blocking=False):
            self._last = now
            self._thread = threading.Thread(target=self._refresh_locked, daemon=True,
                                            name=f"live-payload-{self.machine_id}")
            self._thread.start()
        if self.kg is not None:
            return self.kg
        prog = self.backend.cached_progress(self.machine_id)
        return prog.last_payload_kg if prog is not None else None

    def join(self, timeout_s: float = 10.0) -> None:
        """Wait for a running refresh (tests, shutdown)."""
        t = self._thread
        if t is not None:
            t.join(timeout_s)

    def _refresh_locked(self) -> None:
        try:
            self.refresh()
        finally:
            self._busy.release()

    def refresh(self) -> float | None:
        """Replay the newest ``span_s`` of samples now and update :attr:`kg` (blocking).

        Returns:
            The new estimate [kg] (the previous one when nothing new is stored), or None when
            there is too little data or the replay failed (the previous estimate is kept).
        """
        from cranetwin.service.replayer import sample_rate_hz

        try:
            self.backend.progress(self.machine_id)  # the fallback, for a worker elsewhere
            dr = self.backend.data_range(self.machine_id)
            if dr is None or dr[1] - dr[0] < 2.0 * self.margin_s + 1.0:
                return None
            if dr[1] == self._end:  # nothing new stored since the last estimate
                return self.kg
            samples = self.backend.read_samples(self.machine_id, dr[1] - self.span_s,
                                                dr[1] + 1.0)
            if samples.t_s.shape[0] < 8:
                return None
            grid_hz = sample_rate_hz(samples)
            res = self.replayer.replay(self.machine_id, self.machine, samples, grid_hz)
        except CraneTwinError as exc:
            log.debug("live payload of %s not estimated: %s", self.machine_id, exc)
            return None
        t_end = float(samples.t_s[-1]) - self.margin_s
        sel = (res.t_s <= t_end) & (res.t_s > t_end - 1.0) & np.isfinite(res.payload_kg)
        if not sel.any():
            return None
        self.kg = float(np.median(res.payload_kg[sel]))
        self.t_s = t_end
        self._end = dr[1]
        return self.kg
