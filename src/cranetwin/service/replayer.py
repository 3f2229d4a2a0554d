"""Replays for the API and the worker, reusing each machine's smoothing choice.

Choosing the Savitzky–Golay windows from the noise level costs about two thirds of a one-minute
replay; the noise level is a property of the machine's sensors, not of the minute. So the first
replay of a machine with at least ``MIN_CHOICE_S`` of data chooses, and later replays of the same
machine and channel layout reuse the choice (``ReplayOptions.smoothing``) until
``REFRESH_S`` has passed.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice
from cranetwin.twin import ReplayOptions, TwinResult, replay

MIN_CHOICE_S = 20.0
REFRESH_S = 3600.0


def nominal_period(t_s: np.ndarray) -> float | None:
    """Median sample spacing [s], snapped to 1/whole Hz when within 1e-4 of it (epoch
    timestamps in float64 carry ~1e-7 s of rounding that would otherwise drift the grid)."""
    if t_s.shape[0] < 2:
        return None
    p = float(np.median(np.diff(t_s)))
    if p <= 0:
        return None
    hz = round(1.0 / p)
    return 1.0 / hz if hz >= 1 and abs(hz * p - 1.0) < 1e-4 else p


class Replayer:
    """Thread-safe replay with per-(machine, channels) cached smoothing choices."""

    def __init__(self) -> None:
        self._choices: dict[tuple[str, tuple[str, ...]],
                            tuple[float, tuple[SmoothingChoice, ...]]] = {}
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
        period = nominal_period(samples.t_s)
        opts = ReplayOptions(grid_hz=grid_hz, smoothing=choices, sample_period_s=period,
                             theta0_initial=theta0_initial)
        res = replay(samples, machine, grid_hz=grid_hz, options=opts)
        span = float(samples.t_s[-1] - samples.t_s[0]) if samples.t_s.shape[0] else 0.0
        if choices is None and span >= MIN_CHOICE_S and res.smoothing:
            with self._lock:
                self._choices[key] = (now, tuple(res.smoothing.values()))
        return res
