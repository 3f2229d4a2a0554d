"""A generated family of cranes, for validating the twin on data it was not tuned on.

Each member is the built-in machine with its loads and hydraulics changed
(:class:`CraneVariant`):

* **Force scale k** (×0.1 … ×2): every body's mass and inertia, the tool, the rated load and
  the scenario's payload are multiplied by k, so every cylinder force (gravity and inertia)
  scales by k. Up to k = 1 the cylinders stay the same, so the pressures fall with k (the hard
  case: a force range that is a small share of what the pressure sensors span). Above 1 the
  built-in would need more than its supply pressure, so a bigger crane gets bigger cylinders:
  piston and rod areas, valve flow gains, dead volumes and the slewing drive's torque limit
  scale by k too (bores by √k). Pressures then stay as on the built-in, speeds too, and the
  hydraulic natural frequencies (stiffness ∝ B·A²/V ∝ k, mass ∝ k) are unchanged.
* **Friction** (Coulomb and viscous of every cylinder) × a factor.
* **Bulk modulus** (oil and hose) × a factor: softer or stiffer oil columns, so the hydraulic
  oscillations the pressures carry move in frequency.
* **Valve time constant** (every cylinder's spool lag) set to a value in 5–40 ms.

:func:`crane_family` draws the members from a seed; the first is the built-in itself.
:func:`decimate` turns samples recorded at one rate into samples at an integer fraction of it
(exact for quantisation-only sensors, which have no jitter).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cranetwin.errors import SimulationError
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays

FORCE_SCALES = (0.1, 2.0)
"""Range of the force scale k over the family."""


@dataclass(frozen=True)
class CraneVariant:
    """One member of the family (factors relative to the built-in machine).

    Attributes:
        name: Short label (``k0.45-f1.3-b0.8-t12``).
        force_scale: k, the factor on every load (module docstring).
        friction_scale: Factor on every cylinder's Coulomb and viscous friction.
        bulk_scale: Factor on the oil's and the hoses' bulk modulus.
        spool_time_s: Every cylinder valve's spool time constant [s].
    """

    name: str
    force_scale: float
    friction_scale: float
    bulk_scale: float
    spool_time_s: float

    @staticmethod
    def of(force_scale: float, friction_scale: float, bulk_scale: float,
           spool_time_s: float) -> CraneVariant:
        """A variant labelled by its factors."""
        name = (f"k{force_scale:.2f}-f{friction_scale:.1f}-b{bulk_scale:.1f}-"
                f"t{1000 * spool_time_s:.0f}")
        return CraneVariant(name, force_scale, friction_scale, bulk_scale, spool_time_s)


def crane_family(count: int, seed: int = 0) -> tuple[CraneVariant, ...]:
    """The built-in crane and ``count − 1`` generated ones.

    The generated force scales are spread evenly in log over :data:`FORCE_SCALES` (both ends
    included); friction (×0.5 … ×2, log-uniform), bulk modulus (×0.5 … ×1.5) and the valve
    time constant (5 … 40 ms) are drawn from ``seed``.

    Raises:
        SimulationError: ``count`` < 1.
    """
    if count < 1:
        raise SimulationError(f"a family needs at least one crane, got {count}")
    rng = np.random.default_rng(seed)
    out = [CraneVariant.of(1.0, 1.0, 1.0, 0.02)]
    scales = np.geomspace(*FORCE_SCALES, count - 1) if count > 2 else [FORCE_SCALES[0]] * (
        count - 1)
    for k in scales:
        out.append(CraneVariant.of(
            float(k), float(math.exp(rng.uniform(math.log(0.5), math.log(2.0)))),
            float(rng.uniform(0.5, 1.5)), float(rng.uniform(0.005, 0.040))))
    return tuple(out)


def _scaled_inertia(inertia: Any, k: float) -> list[list[float]]:
    return [[float(x) * k for x in row] for row in inertia]


def variant_machine(machine: Machine, variant: CraneVariant) -> Machine:
    """The machine description of a family member (validated like a machine file).

    Args:
        machine: The built-in machine the factors apply to.
        variant: The member.

    Raises:
        SimulationError: The machine has no hydraulics section or a cylinder has no valve.
    """
    k = variant.force_scale
    big = max(1.0, k)  # cylinders grow only for k > 1
    d = machine.model_dump()
    if d.get("hydraulics") is None:
        raise SimulationError(f"machine {machine.name!r} has no hydraulics to vary")
    h = d["hydraulics"]
    d["machine"]["name"] = f"{machine.name}-{variant.name}"
    for body in d["bodies"]:
        body["mass_kg"] *= k
        body["inertia_kgm2"] = _scaled_inertia(body["inertia_kgm2"], k)
        for pm in body.get("folded_point_masses") or []:
            pm["mass_kg"] *= k
    d["load_point"]["tool_mass_kg"] *= k
    d["rated_load"]["payload_kg"] = [p * k for p in d["rated_load"]["payload_kg"]]
    for cyl in d["cylinders"]:
        if cyl.get("valve") is None:
            raise SimulationError(f"cylinder {cyl['name']!r} has no valve")
        cyl["bore_m"] *= math.sqrt(big)
        cyl["rod_m"] *= math.sqrt(big)
        cyl["valve"]["flow_gain"] *= big
        cyl["valve"]["spool_time_constant_s"] = variant.spool_time_s
        base_v0 = cyl.get("dead_volume_m3") or h["dead_volume_m3"]
        cyl["dead_volume_m3"] = base_v0 * big
        fr = cyl["friction"]
        fr["coulomb"] *= variant.friction_scale
        fr["viscous"] *= variant.friction_scale
    for drive in d["torque_drives"]:
        drive["max_torque_nm"] *= big
    h["oil_bulk_modulus_pa"] *= variant.bulk_scale
    h["hose_bulk_modulus_pa"] *= variant.bulk_scale
    return Machine.model_validate(d)


def decimate(samples: SampleArrays, factor: int) -> SampleArrays:
    """Every ``factor``-th sample (from the first): a recording at rate / factor.

    Raises:
        SimulationError: ``factor`` < 1.
    """
    if factor < 1:
        raise SimulationError(f"decimation factor must be >= 1, got {factor}")
    out = samples.take(slice(None, None, factor))
    period = None if samples.period_ns is None else samples.period_ns * factor
    return dataclasses.replace(out, period_ns=period)
