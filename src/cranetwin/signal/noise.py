"""Measurement-error injection and the error measure of the paper's accuracy experiment.

The paper adds "pseudo-random real numbers uniformly distributed in the predefined range" to the
received pressure and position data, the range being a percentage e of the sensor's range, and
reports the normalised RMSE (NRMSE) of the twin's positions and forces against the simulator's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SignalError
from cranetwin.samples import SampleArrays

F64 = npt.NDArray[np.float64]

NOISY_QUANTITIES: tuple[str, ...] = ("pressure_a", "pressure_b", "position")


class SensorChannel(Protocol):
    """What the error model reads of a sensor channel (``cranetwin.model.Channel`` has it)."""

    @property
    def name(self) -> str: ...
    @property
    def quantity(self) -> str: ...
    @property
    def full_range(self) -> float | None: ...


class HasChannels(Protocol):
    """A machine description, as far as the error model reads it: its sensor channels."""

    @property
    def channels(self) -> Sequence[SensorChannel]: ...


def inject_uniform_noise(
    samples: SampleArrays,
    machine: HasChannels,
    level: float,
    seed: int | np.random.Generator,
    quantities: Iterable[str] = NOISY_QUANTITIES,
) -> SampleArrays:
    """Add uniform error in [−e, +e] × channel full range to the sensor channels.

    Args:
        samples: Received samples; NaN stays NaN.
        machine: Machine description; ``machine.channel(name).full_range`` scales the error.
        level: e, the maximum error as a fraction of full range (0.05 = 5 %).
        seed: Seed or generator (same seed, same error).
        quantities: Channel quantities that get noise: by default the pressures and positions, as
            in the paper ("error added to the pressure and position sensor data"); pass
            ``(*NOISY_QUANTITIES, "torque")`` to disturb the slewing torque too. Channels unknown
            to the machine are left untouched.

    Returns:
        New :class:`SampleArrays` with the error added (values not clipped or re-quantised).
    """
    if level < 0:
        raise SignalError(f"noise level must be >= 0, got {level}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    wanted = set(quantities)
    known = {c.name: c for c in machine.channels}
    scale = np.zeros(len(samples.channels))
    for j, name in enumerate(samples.channels):
        ch = known.get(name)
        if ch is not None and ch.quantity in wanted:
            if ch.full_range is None:
                raise SignalError(f"channel {name!r}: sensor range unknown (no min/max); the "
                                  "error is a share of the range")
            scale[j] = level * ch.full_range
    err = rng.uniform(-1.0, 1.0, size=samples.values.shape) * scale[None, :]
    return dataclasses.replace(samples, values=samples.values + err)


def nrmse(estimate: npt.ArrayLike, truth: npt.ArrayLike) -> F64:
    """Normalised RMSE = RMSE / (max − min of the truth), along axis 0, NaNs ignored.

    Args:
        estimate: Shape (n,) or (n, k).
        truth: Same shape.

    Returns:
        NRMSE per column, shape () or (k,) [fraction, not percent].
    """
    e = np.asarray(estimate, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if e.shape != t.shape:
        raise SignalError(f"estimate shape {e.shape} differs from truth shape {t.shape}")
    rmse = np.sqrt(np.nanmean((e - t) ** 2, axis=0))
    span = np.nanmax(t, axis=0) - np.nanmin(t, axis=0)
    if np.any(span <= 0):
        raise SignalError("NRMSE undefined: the true signal is constant")
    return np.asarray(rmse / span, dtype=np.float64)
