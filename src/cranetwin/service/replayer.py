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
"""

from __future__ import annotations

import threading
import time

from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice, nominal_period
from cranetwin.twin import ReplayOptions, TwinResult, replay

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


class Replayer:
    """Thread-safe replay with per-(machine, channels) cached smoothing choices."""

    def __init__(self) -> None:
        self._choices: dict[tuple[str, tuple[str, ...]],
                            tuple[float, tuple[SmoothingChoice, ...]]] = {}
        self._short: dict[tuple[str, tuple[str, ...]],
                          dict[int, tuple[float, tuple[SmoothingChoice, ...]]]] = {}
        """(machine, channels) → samples of a short span → (time, its own choice)."""
        self._lock = threading.Lock()

    def replay(self, machine_id: str, machine: Machine, samples: SampleArrays, grid_hz: float,
               theta0_initial: float = 0.0) -> TwinResult:
        """Replay ``samples`` on a grid of ``grid_hz`` (a multiple of the sample rate).

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
        res = replay(samples, machine, grid_hz=grid_hz, options=opts)
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
