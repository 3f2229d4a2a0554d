"""Hydraulic equations of a valve-controlled double-acting cylinder, as pure functions.

Each function works on numpy arrays and scalars; the ``*_nb`` twins are the same code compiled
with numba (``@njit``) for the simulator's own njit integration loop (scalars or arrays).

* orifice (valve port) flow: Q = Qn·U·sign(Δp)·sqrt(|Δp|)   [m³/s], Qn [m³/(s·V·√Pa)], U [V];
* chamber volumes: VA = Vdead + A1·s, VB = Vdead + A2·(stroke − s)   [m³];
* pressure build-up: dpA/dt = Be/VA·(QA − A1·ds/dt), dpB/dt = Be/VB·(A2·ds/dt − QB)   [Pa/s],
  with QA the flow into chamber A and QB the flow out of chamber B [m³/s];
* cylinder force, paper Eq. 1–2: F = pA·A1 − pB·A2 − (Fc·tanh(v/vc) + b·v)   [N].
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit


def orifice_flow(flow_gain: Any, voltage: Any, dp: Any) -> Any:
    """Q = Qn·U·sign(Δp)·sqrt(|Δp|) [m³/s] (Qn [m³/(s·V·√Pa)], U [V], Δp [Pa])."""
    return flow_gain * voltage * np.sign(dp) * np.sqrt(np.abs(dp))


def valve_flows(flow_gain: Any, voltage: Any, pA: Any, pB: Any, p_supply: Any,
                p_tank: Any) -> tuple[Any, Any]:
    """Flows of a critically lapped 4/3 proportional valve: (QA into A, QB out of B) [m³/s].

    U > 0 connects supply -> A and B -> tank (the rod extends); U < 0 connects supply -> B and
    A -> tank (QA and QB then negative). Pressures [Pa], U [V].
    """
    pos = voltage >= 0
    qa = orifice_flow(flow_gain, voltage, np.where(pos, p_supply - pA, pA - p_tank))
    qb = orifice_flow(flow_gain, voltage, np.where(pos, pB - p_tank, p_supply - pB))
    return qa, qb


def chamber_volumes(dead_volume: Any, area_a: Any, area_b: Any, stroke: Any,
                    s: Any) -> tuple[Any, Any]:
    """(VA, VB) = (Vdead + A1·s, Vdead + A2·(stroke − s)) [m³]; s rod position [m]."""
    return dead_volume + area_a * s, dead_volume + area_b * (stroke - s)


def pressure_rates(bulk_modulus: Any, dead_volume: Any, area_a: Any, area_b: Any, stroke: Any,
                   s: Any, v: Any, qa: Any, qb: Any) -> tuple[Any, Any]:
    """(dpA/dt, dpB/dt) [Pa/s] = (Be/VA·(QA − A1·v), Be/VB·(A2·v − QB)).

    Args:
        bulk_modulus: Effective bulk modulus Be [Pa] (oil and hose in series).
        dead_volume: Hose + port volume per chamber [m³].
        area_a, area_b: Piston and annulus areas A1, A2 [m²].
        stroke: Cylinder stroke [m].
        s, v: Rod position [m] and velocity [m/s].
        qa, qb: Flow into A and out of B [m³/s].
    """
    va = dead_volume + area_a * s
    vb = dead_volume + area_b * (stroke - s)
    return bulk_modulus / va * (qa - area_a * v), bulk_modulus / vb * (area_b * v - qb)


def cylinder_force_raw(pA: Any, pB: Any, v: Any, area_a: Any, area_b: Any, coulomb: Any,
                       coulomb_velocity: Any, viscous: Any) -> Any:
    """Eq. 1–2 with plain numbers: F = pA·A1 − pB·A2 − (Fc·tanh(v/vc) + b·v) [N]."""
    return pA * area_a - pB * area_b - (coulomb * np.tanh(v / coulomb_velocity) + viscous * v)


def _scalar_valve_flows(flow_gain: float, voltage: float, pA: float, pB: float,
                        p_supply: float, p_tank: float) -> tuple[float, float]:
    if voltage >= 0:
        dpa = p_supply - pA
        dpb = pB - p_tank
    else:
        dpa = pA - p_tank
        dpb = p_supply - pB
    qa = flow_gain * voltage * np.sign(dpa) * np.sqrt(np.abs(dpa))
    qb = flow_gain * voltage * np.sign(dpb) * np.sqrt(np.abs(dpb))
    return qa, qb


orifice_flow_nb = njit(cache=True)(orifice_flow)
valve_flows_nb = njit(cache=True)(_scalar_valve_flows)  # scalars only
chamber_volumes_nb = njit(cache=True)(chamber_volumes)
pressure_rates_nb = njit(cache=True)(pressure_rates)
cylinder_force_nb = njit(cache=True)(cylinder_force_raw)
