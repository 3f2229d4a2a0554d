"""Replays for the fleet service, the live payload and the worker, reusing each machine's
smoothing choice.

Choosing the Savitzky–Golay windows from the noise level costs about two thirds of a one-minute
replay; the noise level is a property of the machine's sensors, not of the minute. So the first
replay of a machine with at least ``MIN_CHOICE_S`` of data chooses, and later replays of the same
machine and channel layout reuse the choice (``ReplayOptions.smoothing``) until
``REFRESH_S`` has passed.

A span with fewer samples than a kept window (the worker's spans of a few seconds at 10 Hz,
where the fixed windows reach 131 samples) cannot use the machine's choice: it chooses on its own
samples, and that choice is kept for the machine's next spans of the same number of samples
(``SHORT_KEPT`` lengths per machine and channel layout, refreshed as the others): choosing cost
more than the rest of such a span's replay, at every span.

The sample period is the one the data carry (:attr:`SampleArrays.period_ns`, what the wire and
storage hold); it is estimated from the sample times only for data that carry none
(:func:`sample_period_s`).

A known payload stored for the samples' span (:meth:`cranetwin.storage.Store.read_payload`, the
imported ``[payload]`` column, docs/IMPORT.md) is the payload of the replay's inverse dynamics
where known, the estimate elsewhere: it is carried to the sample times by
:func:`cranetwin.twin.known_payload.at_instants` (at a stored time its value; the replay's gap
limit between stored times) and passed as ``payload=``. Where none is stored the replay is as
without one.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from cranetwin.model import Machine
from cranetwin.samples import F64, SampleArrays
from cranetwin.signal import SmoothingChoice, nominal_period
from cranetwin.storage.payloads import PayloadSeries
from cranetwin.twin import ReplayOptions, TwinResult, replay
from cranetwin.twin.known_payload import at_instants

MIN_CHOICE_S = 20.0
REFRESH_S = 3600.0
SHORT_KEPT = 4
"""Span lengths [samples] whose own choice is kept per machine and channel layout (the worker's
spans take one or two lengths in steady state)."""


def sample_period_s(samples: SampleArrays) -> float:
    """The sample period of ``samples`` [s]: ``period_ns`` as the source carried it, else (data
    without one) estimated from the sample times by :func:`cranetwin.signal.nominal_period`.

    Raises:
        SignalError: No period carried, and fewer than 2 samples or times not increasing.
    """
    if samples.period_ns is not None:
        return samples.period_ns * 1e-9
    return nominal_period(samples.t_s)


def sample_rate_hz(samples: SampleArrays) -> float:
    """The sample rate of ``samples`` as a whole number of Hz, at least 1 [Hz] (the replay grid
    of the worker, the live payload and the analytics; a multiple of it for the twin view).

    Raises:
        SignalError: As :func:`sample_period_s`.
    """
    return max(1.0, float(round(1.0 / sample_period_s(samples))))


PayloadReader = Callable[[str, float, float], PayloadSeries]
"""(machine id, t0 [s], t1 [s]) → the stored known payload with t0 ≤ t < t1
(:meth:`cranetwin.storage.Store.read_payload`)."""


class Replayer:
    """Thread-safe replay with per-(machine, channels) cached smoothing choices.

    Args:
        payload_of: Reads a machine's stored known payload (module docstring); None: always
            estimated.
    """

    def __init__(self, payload_of: PayloadReader | None = None) -> None:
        self.payload_of = payload_of
        self._choices: dict[tuple[str, tuple[str, ...]],
                            tuple[float, tuple[SmoothingChoice, ...]]] = {}
        self._short: dict[tuple[str, tuple[str, ...]],
                          dict[int, tuple[float, tuple[SmoothingChoice, ...]]]] = {}
        """(machine, channels) → samples of a short span → (time, its own choice)."""
        self._lock = threading.Lock()

    def replay(self, machine_id: str, machine: Machine, samples: SampleArrays, grid_hz: float,
               theta0_initial: float = 0.0, payload_stored: bool = True) -> TwinResult:
        """Replay ``samples`` on a grid of ``grid_hz`` (a multiple of the sample rate).

        Args:
            payload_stored: False when the caller knows no known payload is stored for these
                samples (the twin worker's pass read the machine's payload runs): not read.

        Raises:
            TwinError: The samples cannot be replayed (too few, channels missing, …).
        """
        key = (machine_id, samples.channels)
        now = time.monotonic()
        with self._lock:
            hit = self._choices.get(key)
        choices = hit[1] if hit is not None and now - hit[0] < REFRESH_S else None
        n = samples.t_s.shape[0]
        short = choices is not None and any(not c.adaptive and c.window > n for c in choices)
        if short:  # a window longer than these samples: choose on them (as before the choice
            # was kept; a span of low-rate samples after a smooth stretch failed), or take
            # the choice made so on the machine's last span of as many samples
            with self._lock:
                got = self._short.get(key, {}).get(n)
            choices = got[1] if got is not None and now - got[0] < REFRESH_S else None
        period = sample_period_s(samples) if samples.t_s.shape[0] >= 2 else None
        opts = ReplayOptions(grid_hz=grid_hz, smoothing=choices, sample_period_s=period,
                             theta0_initial=theta0_initial)
        known = self.known_payload(machine_id, samples, period) if payload_stored else None
        res = replay(samples, machine, grid_hz=grid_hz, payload=known, options=opts)
        span = float(samples.t_s[-1] - samples.t_s[0]) if samples.t_s.shape[0] else 0.0
        if choices is None and res.smoothing:
            if short:
                with self._lock:
                    kept = self._short.setdefault(key, {})
                    kept.pop(n, None)
                    kept[n] = (now, tuple(res.smoothing.values()))
                    while len(kept) > SHORT_KEPT:  # the length chosen longest ago goes
                        del kept[next(iter(kept))]
            elif span >= MIN_CHOICE_S:
                with self._lock:
                    self._choices[key] = (now, tuple(res.smoothing.values()))
        return res

    def known_payload(self, machine_id: str, samples: SampleArrays,
                      period_s: float | None) -> F64 | None:
        """The stored known payload at the sample times [kg], shape (n,), NaN where not
        known; None when none is stored for them (or no reader is set)."""
        n = samples.t_s.shape[0]
        if self.payload_of is None or n == 0:
            return None
        p = period_s if period_s is not None else 0.0
        got = self.payload_of(machine_id, float(samples.t_s[0]), float(samples.t_s[-1]) + p
                              + 1e-3)
        if not got.known:
            return None
        kg = at_instants(samples.t_s, got.t_s, got.payload_kg, 5.0 * p)
        return kg if bool(np.isfinite(kg).any()) else None


class RangeReader(Protocol):
    """What :func:`read_range` reads from (:class:`cranetwin.storage.Store`, sharded or not)."""

    def read_samples(self, machine_id: str, t0_s: float, t1_s: float) -> SampleArrays: ...

    def read_payload(self, machine_id: str, t0_s: float, t1_s: float) -> PayloadSeries: ...


def read_range(store: RangeReader, machine_id: str, t0_s: float, t1_s: float
               ) -> tuple[SampleArrays, F64 | None]:
    """A stored range's samples (t0_s ≤ t < t1_s [s]) and the known payload stored with them
    at the sample times [kg], shape (n,), NaN where not known (None: none stored), as every
    replay of stored data takes it (``cranetwin replay --machine``, ``calibrate --machine``,
    the report's direct path; the worker's windows through :class:`Replayer`)."""
    samples = store.read_samples(machine_id, t0_s, t1_s)
    n = samples.t_s.shape[0]
    if n == 0:
        return samples, None
    known = Replayer(store.read_payload).known_payload(
        machine_id, samples, sample_period_s(samples) if n >= 2 else None)
    return samples, known
