"""Sensor-error models for validating the twin on data it was not tuned on.

:func:`cranetwin.signal.inject_uniform_noise` is the paper's error (uniform in ±e of each
sensor's full range). Real loggers differ: the error may be Gaussian, and it may be a share of
what the channel actually recorded rather than of the sensor's range (a 250 bar sensor on a
cylinder that never sees more than 40 bar). :func:`inject_error` covers those combinations so
that accuracy claims (the payload's σ, the force observability flag) are checked on more than
one error model. Besides random error it makes the two a filter cannot average away: a coarse
quantisation (a staircase, the same on every run) and a constant offset per channel (bias).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Literal

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SimulationError
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays

F64 = npt.NDArray[np.float64]

NOISY_QUANTITIES: tuple[str, ...] = ("pressure_a", "pressure_b", "position")

Distribution = Literal["uniform", "gaussian", "quantised", "biased"]
DISTRIBUTIONS: tuple[Distribution, ...] = ("uniform", "gaussian", "quantised", "biased")
Scale = Literal["full", "recorded"]


def error_ranges(samples: SampleArrays, machine: Machine, scale: Scale,
                 quantities: Iterable[str] = NOISY_QUANTITIES) -> F64:
    """R per column of ``samples`` (``samples.channels`` order) [channel unit]: the sensor's
    full range (``"full"``) or the range the column recorded (``"recorded"``, max − min); 0
    for the columns of other quantities or not in the machine.

    Raises:
        SimulationError: ``"full"`` on a channel whose sensor range is unknown.
    """
    wanted = set(quantities)
    known = {c.name: c for c in machine.channels}
    r = np.zeros(len(samples.channels))
    for j, name in enumerate(samples.channels):
        ch = known.get(name)
        if ch is None or ch.quantity not in wanted:
            continue
        if scale == "full":
            if ch.full_range is None:
                raise SimulationError(f"channel {name!r}: sensor range unknown (no min/max); "
                                      "use scale=\"recorded\"")
            r[j] = ch.full_range
        else:
            col = samples.values[:, j]
            col = col[np.isfinite(col)]
            r[j] = float(col.max() - col.min()) if col.size else 0.0
    return r


def data_sheet(samples: SampleArrays, machine: Machine, level: float, scale: Scale,
               quantities: Iterable[str] = NOISY_QUANTITIES) -> Machine:
    """The machine with each error-bearing channel's stated accuracy (``Channel.accuracy``)
    set to the bound of :func:`inject_error`'s error, e·R (R of :func:`error_ranges`): what a
    data sheet would state for sensors that err that much. ``samples`` are the clean ones
    (for ``"recorded"``: the error's R was taken from them). Channels with R = 0 keep theirs.

    Raises:
        SimulationError: A negative level, or as :func:`error_ranges`.
    """
    if level < 0:
        raise SimulationError(f"error level must be >= 0, got {level}")
    bound = dict(zip(samples.channels, level * error_ranges(samples, machine, scale,
                                                            quantities), strict=True))
    chans = [ch.model_copy(update={"accuracy": bound[ch.name]})
             if bound.get(ch.name, 0.0) > 0 else ch for ch in machine.channels]
    return Machine.model_validate({**machine.model_dump(), "channels":
                                   [c.model_dump() for c in chans]})


def inject_error(samples: SampleArrays, machine: Machine, level: float, seed: int,
                 distribution: Distribution = "uniform", scale: Scale = "full",
                 quantities: Iterable[str] = NOISY_QUANTITIES) -> SampleArrays:
    """Add independent random error to the pressure and position channels.

    Args:
        samples: Clean samples; NaN stays NaN.
        machine: Machine description (channel ranges).
        level: e as a fraction (0.02 = 2 %).
        seed: Seed of the error (same seed, same error).
        distribution: ``"uniform"``: uniform in [−e, +e] × R (σ = e·R/√3); ``"gaussian"``:
            normal with σ = e·R; ``"quantised"``: the value rounded to steps of 2·e·R (error
            within ±e·R, deterministic: the seed is not used); ``"biased"``: a constant offset
            per channel, uniform in [−e/2, +e/2] × R, plus uniform error in [−e/2, +e/2] × R
            (within ±e·R; half of it no smoothing removes).
        scale: R is the sensor's full range (``"full"``, ``Channel.full_range``) or the range
            the channel recorded in ``samples`` (``"recorded"``, max − min).
        quantities: Channel quantities that get error.

    Returns:
        New :class:`SampleArrays` (values not clipped or re-quantised).

    Raises:
        SimulationError: A negative level or an unknown distribution or scale.
    """
    if level < 0:
        raise SimulationError(f"error level must be >= 0, got {level}")
    if distribution not in DISTRIBUTIONS or scale not in ("full", "recorded"):
        raise SimulationError(f"unknown error model {distribution!r} / {scale!r}")
    rng = np.random.default_rng(seed)
    r = error_ranges(samples, machine, scale, quantities)
    shape = samples.values.shape
    amp = (level * r)[None, :]
    if distribution == "quantised":
        step = np.where(amp > 0, 2.0 * amp, 1.0)
        values = np.where(amp > 0, np.round(samples.values / step) * step, samples.values)
        return dataclasses.replace(samples, values=values)
    if distribution == "biased":
        offset = rng.uniform(-0.5, 0.5, size=(1, shape[1]))
        unit = offset + rng.uniform(-0.5, 0.5, size=shape)
    elif distribution == "uniform":
        unit = rng.uniform(-1.0, 1.0, size=shape)
    else:
        unit = rng.standard_normal(size=shape)
    return dataclasses.replace(samples, values=samples.values + unit * amp)
