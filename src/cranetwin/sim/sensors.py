"""Sensor model: what the machine's transducers and data logger make of the true state.

For sample k (nominal time k/rate), the logger really samples at ``k/rate + e_k`` (clock jitter
e_k ~ N(0, σ_j), clipped to ±0.4/rate, rounded to the integration step) but stamps the nominal
time, as a fixed-period logger does. Each value then gets

    y = clip(round((x + bias + noise) / resolution) · resolution, min, max)

with the resolution and range of the channel in the machine file, Gaussian noise of standard
deviation ``noise_fraction · (max − min)`` and a per-channel constant bias drawn once per run
(``bias_fraction · (max − min)`` standard deviation). Each sample of each channel is lost (NaN)
with probability ``dropout_probability``; dropouts come in bursts of mean length
``dropout_burst_mean`` samples.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field

from cranetwin.errors import SimulationError
from cranetwin.model import Channel, Machine
from cranetwin.sim.layout import layout_of

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# the integration loop's snapshot columns at each sampling instant: cranetwin.sim.layout


class SensorModel(BaseModel):
    """Sensor and logger imperfections (defaults: a good industrial installation).

    Attributes:
        rate_hz: Sampling rate [Hz].
        noise_fraction: Noise std as a fraction of each channel's full range.
        bias_fraction: Std of the per-channel constant bias, fraction of full range.
        dropout_probability: Probability that a sample of a channel is lost.
        dropout_burst_mean: Mean length of a dropout burst [samples].
        jitter_s: Std of the sampling-instant jitter [s].
        include_optional: Also send optional channels (e.g. ``slew_angle``).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    rate_hz: float = Field(100.0, gt=0, le=10000.0)
    noise_fraction: float = Field(5.0e-4, ge=0, le=0.5)
    bias_fraction: float = Field(2.0e-4, ge=0, le=0.5)
    dropout_probability: float = Field(1.0e-3, ge=0, lt=1)
    dropout_burst_mean: float = Field(3.0, ge=1)
    jitter_s: float = Field(2.0e-4, ge=0)
    include_optional: bool = True

    @classmethod
    def ideal(cls, rate_hz: float = 100.0) -> SensorModel:
        """Quantisation only: no noise, bias, dropouts or jitter."""
        return cls(rate_hz=rate_hz, noise_fraction=0.0, bias_fraction=0.0,
                   dropout_probability=0.0, jitter_s=0.0)


class SampleClock:
    """The logger's sampling schedule, produced chunk by chunk.

    Sample k has the nominal time k/rate; the logger really samples at the integration step
    nearest k/rate + e_k (e_k the clipped jitter), never before the previous sample's step.
    """

    def __init__(self, model: SensorModel, step_s: float, rng: np.random.Generator) -> None:
        self.period = 1.0 / model.rate_hz
        self.step_s = step_s
        self.jitter_s = model.jitter_s
        self.rng = rng
        self.next_k = 0
        self._last_step = 0
        self._jitter = np.zeros(0)     # drawn jitter of samples next_k, next_k + 1, ...

    def take(self, step_end: int, inclusive: bool = False) -> tuple[F64, I64]:
        """Samples whose step index is below ``step_end`` (or equal, if ``inclusive``).

        Returns:
            (nominal times [s] shape (m,), step indices shape (m,), non-decreasing).
        """
        t_end = step_end * self.step_s
        k_max = int(np.floor(t_end / self.period + 0.4 + 1e-9)) + 1   # jitter reach ±0.4 T
        count = max(0, k_max - self.next_k + 1)
        if self._jitter.shape[0] < count:
            extra = count - self._jitter.shape[0]
            new = np.zeros(extra)
            if self.jitter_s > 0:
                new = np.clip(self.rng.normal(0.0, self.jitter_s, extra),
                              -0.4 * self.period, 0.4 * self.period)
            self._jitter = np.concatenate([self._jitter, new])
        k = self.next_k + np.arange(count)
        t_nom = k * self.period
        steps = np.maximum(np.rint((t_nom + self._jitter[:count]) / self.step_s), 0)
        steps = np.maximum.accumulate(np.maximum(steps, self._last_step)).astype(np.int64)
        m = int(np.searchsorted(steps, step_end, side="right" if inclusive else "left"))
        if inclusive:
            # the last sample of a run may not wait for a step beyond the end
            late = (t_nom <= t_end + 1e-12) & (steps > step_end)
            steps[late] = step_end
            m = int(np.count_nonzero(steps <= step_end))
        self.next_k += m
        self._jitter = self._jitter[m:]
        if m:
            self._last_step = int(steps[m - 1])
        return np.asarray(t_nom[:m], dtype=np.float64), steps[:m]


def sample_steps(duration_s: float, step_s: float, model: SensorModel,
                 rng: np.random.Generator) -> tuple[F64, I64]:
    """The whole schedule of a run of ``duration_s``: nominal times and integration steps.

    Returns:
        (t_nominal [s] shape (m,), step indices shape (m,), non-decreasing, within
        [0, round(duration_s/step_s)]).
    """
    return SampleClock(model, step_s, rng).take(int(round(duration_s / step_s)), inclusive=True)


def channel_source_column(machine: Machine, ch: Channel) -> int:
    """Snapshot column that feeds channel ``ch``.

    Raises:
        SimulationError: the simulator does not produce this kind of channel.
    """
    lay = layout_of(machine)
    cyl_names = [c.name for c in machine.cylinders]
    if ch.quantity in ("pressure_a", "pressure_b", "position"):
        if ch.source not in cyl_names:
            raise SimulationError(f"channel {ch.name!r}: {ch.quantity} of {ch.source!r}, "
                                  f"expected one of the cylinders {cyl_names}")
        base = {"pressure_a": lay.snap_pa, "pressure_b": lay.snap_pb,
                "position": lay.snap_s}[ch.quantity]
        return base + cyl_names.index(ch.source)
    if ch.quantity == "torque":
        drives = [d.name for d in machine.torque_drives]
        if ch.source not in drives:
            raise SimulationError(f"channel {ch.name!r}: torque of {ch.source!r}, expected one "
                                  f"of the torque drives {drives}")
        return lay.snap_torque + drives.index(ch.source)
    if ch.quantity == "angle":
        return lay.snap_q + machine.joint_index(ch.source)
    raise SimulationError(f"channel {ch.name!r}: the simulator cannot produce {ch.quantity!r}")


class SensorReader:
    """Turns true values at the sampling instants into channel readings, chunk by chunk
    (per-channel bias drawn once; dropout bursts carry over chunk boundaries)."""

    def __init__(self, machine: Machine, model: SensorModel, rng: np.random.Generator) -> None:
        self.model = model
        self.rng = rng
        self.channels = [c for c in machine.channels if model.include_optional or not c.optional]
        self.names = tuple(c.name for c in self.channels)
        self.columns = [channel_source_column(machine, c) for c in self.channels]
        unknown = [c.name for c in self.channels if c.full_range is None]
        if unknown and (model.noise_fraction > 0 or model.bias_fraction > 0):
            raise SimulationError(
                f"channel(s) {', '.join(unknown)}: sensor range unknown (no min/max); the "
                "sensor model's noise and bias are shares of the range: state the ranges or "
                "simulate with noise_fraction = bias_fraction = 0")
        spans = np.array([c.full_range or 0.0 for c in self.channels])
        self.bias = (rng.normal(0.0, model.bias_fraction * spans) if model.bias_fraction > 0
                     else np.zeros(len(self.channels)))
        self._burst_left = np.zeros(len(self.channels), dtype=np.int64)

    def read(self, snapshots: F64) -> F64:
        """Readings for true values ``snapshots`` (m, n_snap) -> (m, n_channels), NaN = lost."""
        m = snapshots.shape[0]
        model = self.model
        out = np.empty((m, len(self.channels)))
        for j, ch in enumerate(self.channels):
            x = snapshots[:, self.columns[j]] + self.bias[j]
            if model.noise_fraction > 0:
                x = x + self.rng.normal(0.0, model.noise_fraction * (ch.full_range or 0.0), m)
            x = np.round(x / ch.resolution) * ch.resolution
            # a sensor saturates at the ends of its range; an unknown range: not clipped
            out[:, j] = x if ch.min is None or ch.max is None else np.clip(x, ch.min, ch.max)
            if model.dropout_probability > 0:
                out[self._dropouts(m, j), j] = np.nan
        return out

    def _dropouts(self, m: int, j: int) -> npt.NDArray[np.bool_]:
        """Bursty loss mask: burst starts at rate p/L, lengths geometric with mean L."""
        mask = np.zeros(m, dtype=bool)
        carry = int(min(self._burst_left[j], m))
        mask[:carry] = True
        self._burst_left[j] -= carry
        mean = self.model.dropout_burst_mean
        starts = np.flatnonzero(self.rng.uniform(size=m) < self.model.dropout_probability / mean)
        for k in starts:
            end = int(k) + int(self.rng.geometric(1.0 / mean))
            mask[k:end] = True
            self._burst_left[j] = max(int(self._burst_left[j]), end - m)
        return mask


def apply_sensors(machine: Machine, snapshots: F64, model: SensorModel,
                  rng: np.random.Generator) -> tuple[tuple[str, ...], F64]:
    """Readings of a whole run in one go (see :class:`SensorReader`).

    Args:
        machine: Machine description (channels, ranges, resolutions).
        snapshots: True values at the sampling instants, shape (m, n_snap)
            (:mod:`cranetwin.sim.layout`).
        model: Sensor model.
        rng: Random generator (noise, bias, dropouts).

    Returns:
        (channel names, values shape (m, n_channels) [channel units], NaN = dropout).
    """
    reader = SensorReader(machine, model, rng)
    return reader.names, reader.read(snapshots)
