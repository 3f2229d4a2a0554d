"""Can the pressures resolve a cylinder's force? The sensor error against the force range seen.

A cylinder's force comes from its two chamber pressures, F = A_A·p_A − A_B·p_B − friction
(Eq. 1–2). A pressure error σ_p in each chamber is a force error::

    σ_F = sqrt(A_A²·σ_pA² + A_B²·σ_pB²)      (= σ_p·sqrt(A_A² + A_B²) for equal sensors)

per sample, before any smoothing. σ_p is the larger of the sensors' stated accuracy
(``Channel.accuracy``, a ± bound taken as uniform: σ = accuracy/√3) and the noise the replay
estimated from the data (:attr:`cranetwin.signal.SmoothingChoice.sigma` of the pressure pair,
already in N). A channel whose samples lie on a coarse lattice
(:mod:`cranetwin.signal.quantisation`, :attr:`cranetwin.signal.SmoothingChoice.step`) errs by up
to ±step/2, systematically where the signal is slow: its bound is the larger of the stated
accuracy and step/2 (:func:`effective_accuracy`), stated or not. A stated accuracy is mostly
offset and gain error, which no smoothing removes, so σ_F is compared unsmoothed.

Flat pressures. When both chamber pressures read one value each over the whole window
(:attr:`cranetwin.signal.SmoothingChoice.flat`), the sensors show none of the force's
variation and no step to bound their error: a stuck sensor, or a quantisation coarser than the
force's whole variation (a small idle cylinder behind 25 bar steps). The pressure-only force is
then constant (its range 0, share ∞), but a model-based force
(:mod:`cranetwin.twin.force_model`) takes its shape from the inverse dynamics and its level from
those readings, off by up to half an unknown step: such a force is flagged not observable
whatever its share ("flat pressures"). One flat chamber alone (a return line at tank pressure)
is not flagged for it.

When σ_F exceeds ``RESOLVABLE_SHARE`` (10 %) of the range of the cylinder's replayed force
(max − min over the window), the force is flagged as not observable: its shape is then mostly
sensor error (a small telescope cylinder of a few kN behind 0–250 bar sensors: ±1 % of the
pressure range is ±490 N of force).

The systematic floor. Smoothing removes noise; it does not remove what the stated accuracy
leaves beyond the noise seen in the data (an offset, a gain error, a coarse staircase), so the
replayed force's error cannot fall below that part, σ_b,F = max(σ_stated − σ_noise, 0)
(:func:`systematic_force_sigma`, the same σ_b,c the payload's σ carries,
:func:`cranetwin.twin.payload.systematic_std`). When σ_b,F exceeds ``FORCE_ACCURACY_TARGET``
(4 %, the force accuracy the twin is held to: docs/ACCURACY.md "Noise family", target
``force``) of the range, the force is flagged too, whatever the noise share: it cannot meet
that accuracy. Without a stated accuracy σ_b,F = 0 and only the noise share flags.

The flag travels with the replay: :func:`assess`
returns one :class:`ForceObservability` per cylinder, :class:`ForceRange` collects the range
chunk by chunk for streamed replays.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.signal import SmoothingChoice
from cranetwin.twin.payload import systematic_std

F64 = npt.NDArray[np.float64]

RESOLVABLE_SHARE = 0.10
"""A force is observable when its per-sample error σ_F is at most this share of its range."""

FORCE_ACCURACY_TARGET = 0.04
"""The force accuracy the twin is held to: NRMSE (RMS error over the true force's range) at
most 4 % (the noise family's force target, docs/ACCURACY.md "Noise family"). A force whose
systematic error floor σ_b,F exceeds this share of its range is flagged not observable (module
docstring)."""

Cause = Literal["noise share", "systematic floor", "flat pressures"]


class ForceObservability(NamedTuple):
    """Whether one cylinder's force can be resolved in a replayed window.

    Attributes:
        cylinder: Cylinder name.
        sigma_n: Per-sample force error σ_F [N] (module docstring).
        source: Where σ_p came from: the sensors' stated accuracy or the data's noise.
        range_n: Range of the replayed force in the window, max − min [N].
        share: sigma_n / range_n (inf for a constant force).
        observable: share ≤ ``RESOLVABLE_SHARE`` and systematic_share ≤
            ``FORCE_ACCURACY_TARGET``.
        systematic_n: The systematic floor σ_b,F [N] (module docstring; 0 without a stated
            accuracy).
        systematic_share: systematic_n / range_n (inf for a constant force with a floor).
        flat: Both pressures read one value over the window (module docstring).
    """

    cylinder: str
    sigma_n: float
    source: Literal["stated accuracy", "estimated noise"]
    range_n: float
    share: float
    observable: bool
    systematic_n: float = 0.0
    systematic_share: float = 0.0
    flat: bool = False

    @property
    def causes(self) -> tuple[Cause, ...]:
        """Why the force is not observable (empty when it is): the noise share over
        ``RESOLVABLE_SHARE``, the systematic floor over ``FORCE_ACCURACY_TARGET``, flat
        pressures, or several."""
        out: list[Cause] = []
        if not self.share <= RESOLVABLE_SHARE:
            out.append("noise share")
        if not self.systematic_share <= FORCE_ACCURACY_TARGET:
            out.append("systematic floor")
        if self.flat:
            out.append("flat pressures")
        return tuple(out)

    def message(self) -> str:
        """One line naming the cylinder, the numbers and, when flagged, the cause."""
        verdict = "observable" if self.observable else \
            f"NOT observable ({' and '.join(self.causes)})"
        line = (f"cylinder {self.cylinder!r}: force {verdict}: pressure error "
                f"±{self.sigma_n:.0f} N (1σ, {self.source}) against a force range of "
                f"{self.range_n:.0f} N "
                f"({100 * self.share:.0f} %; limit {100 * RESOLVABLE_SHARE:.0f} %)")
        if self.systematic_n > 0:
            line += (f"; systematic floor ±{self.systematic_n:.0f} N (stated accuracy beyond "
                     f"the noise) = {100 * self.systematic_share:.1f} % "
                     f"(limit {100 * FORCE_ACCURACY_TARGET:.0f} %)")
        if self.flat:
            line += ("; both pressures read one value throughout: the sensors show none of "
                     "the force's variation")
        return line

    def as_json(self) -> dict[str, Any]:
        """Plain numbers for the API (shares None when infinite)."""
        def num(x: float) -> float | None:
            return None if not math.isfinite(x) else round(x, 4)

        return {"cylinder": self.cylinder, "sigma_n": round(self.sigma_n, 1),
                "source": self.source, "range_n": round(self.range_n, 1),
                "share": num(self.share), "observable": self.observable,
                "systematic_n": round(self.systematic_n, 1),
                "systematic_share": num(self.systematic_share),
                "flat": self.flat, "causes": list(self.causes)}


def effective_accuracy(stated: float | None, step: float) -> float | None:
    """A channel's ± error bound [channel unit]: the larger of its stated accuracy and half
    the quantisation step detected in its data (``step`` 0: none detected); None when neither
    is known."""
    half = 0.5 * step if step > 0 else None
    if stated is None:
        return half
    return stated if half is None else max(stated, half)


def channel_steps(smoothing: Mapping[str, SmoothingChoice] | None) -> dict[str, float]:
    """The quantisation step detected per channel name [channel unit] (0: none), from the
    replay's smoothing choices."""
    return {} if smoothing is None else {n: c.step for n, c in smoothing.items()}


def stated_force_sigma(machine: Machine, cylinder: int,
                       steps: Mapping[str, float] | None = None) -> float:
    """σ_F [N] from the ± bounds (:func:`effective_accuracy`: stated accuracy, or half the
    detected quantisation step ``steps[name]``) of the cylinder's two pressure channels.

    0 when either channel states no accuracy and neither shows a step (a data sheet for one
    chamber only is taken as incomplete). A detected step is evidence from the data and is
    kept even when the other chamber shows none (a chamber held at one level, e.g. at tank
    pressure, shows no step): that chamber then counts 0."""
    cyl = machine.cylinders[cylinder]
    acc: dict[str, float | None] = {}
    detected = False
    for ch in machine.channels:
        if ch.source == cyl.name and ch.quantity in ("pressure_a", "pressure_b"):
            step = (steps or {}).get(ch.name, 0.0)
            detected |= step > 0
            acc[ch.quantity] = effective_accuracy(ch.accuracy, step)
    if len(acc) < 2 or (not detected and None in acc.values()):
        return 0.0
    a, b = (acc[q] or 0.0 for q in ("pressure_a", "pressure_b"))
    return math.hypot(cyl.area_a_m2 * a, cyl.area_b_m2 * b) / math.sqrt(3.0)


def systematic_force_sigma(machine: Machine, noise_n: F64,
                           steps: Mapping[str, float] | None = None) -> F64:
    """σ_b,F per cylinder, shape (n_c,) [N]: what the stated accuracy (raised to half a
    detected quantisation step, ``steps`` as :func:`stated_force_sigma`) leaves beyond the raw
    force noise ``noise_n`` (n_c,) [N] estimated from the data
    (:func:`cranetwin.twin.payload.systematic_std`; 0 where nothing is stated or detected).
    The payload's σ and the observability flag both take it from here."""
    stated = np.array([stated_force_sigma(machine, c, steps)
                       for c in range(len(machine.cylinders))])
    return systematic_std(stated, np.asarray(noise_n, dtype=np.float64))


def estimated_force_noise(machine: Machine, cylinder: int,
                          smoothing: Mapping[str, SmoothingChoice]) -> float:
    """Raw force noise σ [N] the replay estimated for one cylinder (the pressure pair's
    smoothing choice, keyed by the pA channel's name; 0 when it has none)."""
    cyl = machine.cylinders[cylinder]
    est = 0.0
    for ch in machine.channels:
        if ch.source == cyl.name and ch.quantity == "pressure_a" and ch.name in smoothing:
            est = max(smoothing[ch.name].sigma, 0.0)
    return est


def force_sigma(machine: Machine, cylinder: int,
                smoothing: Mapping[str, SmoothingChoice]) -> tuple[float, Literal[
                    "stated accuracy", "estimated noise"]]:
    """(σ_F [N], its source) for one cylinder: the larger of the stated accuracy's (or half
    the detected quantisation step's, :func:`effective_accuracy`) and the estimated noise's
    (:func:`estimated_force_noise`)."""
    est = estimated_force_noise(machine, cylinder, smoothing)
    stated = stated_force_sigma(machine, cylinder, channel_steps(smoothing))
    return (stated, "stated accuracy") if stated >= est else (est, "estimated noise")


def assess(machine: Machine, smoothing: Mapping[str, SmoothingChoice], force_min_n: F64,
           force_max_n: F64) -> tuple[ForceObservability, ...]:
    """One :class:`ForceObservability` per cylinder (``machine.cylinders`` order).

    Args:
        machine: The machine (areas, channels and their stated accuracy).
        smoothing: The replay's smoothing choices (:attr:`TwinResult.smoothing`).
        force_min_n, force_max_n: Smallest and largest replayed force per cylinder, (n_c,) [N].
    """
    out = []
    noise = np.array([estimated_force_noise(machine, k, smoothing)
                      for k in range(len(machine.cylinders))])
    floor = systematic_force_sigma(machine, noise, channel_steps(smoothing))
    for k, cyl in enumerate(machine.cylinders):
        sigma, source = force_sigma(machine, k, smoothing)
        span = float(force_max_n[k] - force_min_n[k])
        share = _share(sigma, span)
        sys_share = _share(float(floor[k]), span)
        pair = [smoothing[ch.name].flat for ch in machine.channels
                if ch.source == cyl.name and ch.quantity in ("pressure_a", "pressure_b")
                and ch.name in smoothing]
        flat = len(pair) == 2 and all(pair)
        out.append(ForceObservability(
            cyl.name, sigma, source, span, share,
            bool(share <= RESOLVABLE_SHARE and sys_share <= FORCE_ACCURACY_TARGET and not flat),
            float(floor[k]), sys_share, flat))
    return tuple(out)


def _share(sigma: float, span: float) -> float:
    """sigma / span; 0 for no error, inf for an error on a constant force."""
    return sigma / span if span > 0 else (0.0 if sigma == 0 else math.inf)


@dataclass
class ForceRange:
    """The replayed force's range per cylinder, collected over the chunks of a replay."""

    lo: F64 = field(default_factory=lambda: np.zeros(0))
    hi: F64 = field(default_factory=lambda: np.zeros(0))

    def add(self, force_n: F64) -> None:
        """Take in a chunk's cylinder forces, (m, n_c) [N] (non-finite values ignored)."""
        if force_n.shape[0] == 0:
            return
        f = np.where(np.isfinite(force_n), force_n, np.nan)
        with np.errstate(all="ignore"):
            lo = np.nan_to_num(np.nanmin(f, axis=0), nan=np.inf)
            hi = np.nan_to_num(np.nanmax(f, axis=0), nan=-np.inf)
        if self.lo.shape[0] == 0:
            self.lo, self.hi = lo, hi
        else:
            self.lo = np.minimum(self.lo, lo)
            self.hi = np.maximum(self.hi, hi)

    def assess(self, machine: Machine,
               smoothing: Mapping[str, SmoothingChoice]) -> tuple[ForceObservability, ...]:
        """:func:`assess` over what was added (nothing added: no verdicts)."""
        if self.lo.shape[0] == 0:
            return ()
        span_ok = self.hi >= self.lo
        return assess(machine, smoothing, np.where(span_ok, self.lo, 0.0),
                      np.where(span_ok, self.hi, 0.0))


def unobservable(verdicts: tuple[ForceObservability, ...]) -> list[str]:
    """The warning lines of the cylinders whose force is not observable."""
    return [v.message() for v in verdicts if not v.observable]
