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

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# snapshot columns recorded by the integration loop at each sampling instant
SNAP_PA, SNAP_PB, SNAP_S = 0, 3, 6           # + cylinder index (machine order)
SNAP_SLEW_TORQUE, SNAP_Q = 9, 10             # + joint index for SNAP_Q
N_SNAP = 14


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


def sample_steps(duration_s: float, step_s: float, model: SensorModel,
                 rng: np.random.Generator) -> tuple[F64, I64]:
    """Nominal sample times and the integration steps at which the logger really samples.

    Returns:
        (t_nominal [s] shape (m,), step indices shape (m,), non-decreasing, within
        [0, round(duration_s/step_s)]).
    """
    period = 1.0 / model.rate_hz
    n_steps = int(round(duration_s / step_s))
    m = int(np.floor(duration_s * model.rate_hz + 1e-9)) + 1
    t_nom = np.arange(m, dtype=np.float64) * period
    jitter = np.zeros(m)
    if model.jitter_s > 0:
        jitter = np.clip(rng.normal(0.0, model.jitter_s, m), -0.4 * period, 0.4 * period)
    steps = np.clip(np.rint((t_nom + jitter) / step_s), 0, n_steps).astype(np.int64)
    steps = np.maximum.accumulate(steps).astype(np.int64)
    return t_nom, steps


def channel_source_column(machine: Machine, ch: Channel) -> int:
    """Snapshot column that feeds channel ``ch``.

    Raises:
        SimulationError: the simulator does not produce this kind of channel.
    """
    cyl_names = [c.name for c in machine.cylinders]
    if ch.quantity in ("pressure_a", "pressure_b", "position"):
        if ch.source not in cyl_names:
            raise SimulationError(f"channel {ch.name!r}: {ch.quantity} of {ch.source!r}, "
                                  f"expected one of the cylinders {cyl_names}")
        base = {"pressure_a": SNAP_PA, "pressure_b": SNAP_PB, "position": SNAP_S}[ch.quantity]
        return base + cyl_names.index(ch.source)
    if ch.quantity == "torque":
        return SNAP_SLEW_TORQUE
    if ch.quantity == "angle":
        return SNAP_Q + machine.joint_index(ch.source)
    raise SimulationError(f"channel {ch.name!r}: the simulator cannot produce {ch.quantity!r}")


def apply_sensors(machine: Machine, snapshots: F64, model: SensorModel,
                  rng: np.random.Generator) -> tuple[tuple[str, ...], F64]:
    """Turn true values at the sampling instants into channel readings.

    Args:
        machine: Machine description (channels, ranges, resolutions).
        snapshots: True values at the sampling instants, shape (m, N_SNAP).
        model: Sensor model.
        rng: Random generator (noise, bias, dropouts).

    Returns:
        (channel names, values shape (m, n_channels) [channel units], NaN = dropout).
    """
    chans = [c for c in machine.channels if model.include_optional or not c.optional]
    m = snapshots.shape[0]
    out = np.empty((m, len(chans)))
    for j, ch in enumerate(chans):
        x = snapshots[:, channel_source_column(machine, ch)].copy()
        span = ch.full_range
        if model.bias_fraction > 0:
            x += rng.normal(0.0, model.bias_fraction * span)
        if model.noise_fraction > 0:
            x += rng.normal(0.0, model.noise_fraction * span, m)
        x = np.round(x / ch.resolution) * ch.resolution
        out[:, j] = np.clip(x, ch.min, ch.max)
        if model.dropout_probability > 0:
            out[_dropout_mask(m, model, rng), j] = np.nan
    return tuple(c.name for c in chans), out


def _dropout_mask(m: int, model: SensorModel, rng: np.random.Generator) -> npt.NDArray[np.bool_]:
    """Bursty loss mask: burst starts at rate p/L, lengths geometric with mean L."""
    mask = np.zeros(m, dtype=bool)
    mean = model.dropout_burst_mean
    starts = np.flatnonzero(rng.uniform(size=m) < model.dropout_probability / mean)
    for k in starts:
        length = int(rng.geometric(1.0 / mean))
        mask[k:k + length] = True
    return mask
