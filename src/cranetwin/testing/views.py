"""Synthetic crane data in the API's JSON shapes, for UI previews and the web tests.

A scripted work cycle (slew, lift, jib and telescope on smooth sinusoids inside the joint limits,
a log of ``payload_kg`` grabbed for the middle half of every 40 s cycle) is turned into body poses
and cylinder pins by :mod:`cranetwin.physics` kinematics. Cylinder forces here are a simple
quasi-static estimate (payload and boom weight times reach over a fixed lever) — plausible numbers
for drawing, NOT the twin's inverse dynamics; nothing outside previews and tests may use them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.physics.kinematics import horizontal_reach
from cranetwin.viz.poses import frame_arrays

F64 = npt.NDArray[np.float64]
CYCLE_S = 40.0
"""Period of the scripted work cycle [s]."""


def scripted_q(t: F64, phase: float = 0.0) -> F64:
    """Joint positions of the scripted cycle at times t [s], shape (n, 4) [rad, rad, rad, m]."""
    t = np.asarray(t, dtype=float) + phase
    w = 2 * np.pi / CYCLE_S
    return np.stack([
        1.2 * np.sin(w * t),
        0.5 + 0.35 * np.sin(2 * w * t),
        -1.6 + 0.5 * np.sin(2 * w * t + 1.0),
        0.6 + 0.5 * np.sin(w * t + 0.5),
    ], axis=1)


def scripted_payload(t: F64, payload_kg: float, phase: float = 0.0) -> F64:
    """Payload [kg] at times t [s]: ``payload_kg`` during the middle half of each cycle."""
    frac = np.mod(np.asarray(t, dtype=float) + phase, CYCLE_S) / CYCLE_S
    return np.where((frac > 0.25) & (frac < 0.75), payload_kg, 0.0)


def _loads(machine: Machine, q: F64, payload: F64) -> dict[str, Any]:
    reach = horizontal_reach(machine, q)
    g = 9.81
    moment1 = g * (payload + machine.load_point.tool_mass_kg + 150.0) * reach
    moment2 = g * (payload + machine.load_point.tool_mass_kg + 60.0) * np.maximum(reach - 2.5, 0.3)
    forces = {}
    util = {}
    pressures = {}
    supply = machine.hydraulics.supply_pressure_pa if machine.hydraulics else 16e6
    levers = {"lift": 0.35, "jib": 0.3}
    for k, cyl in enumerate(machine.cylinders):
        if k == 0:
            f = moment1 / levers.get(cyl.name, 0.35)
        elif k == 1:
            f = -moment2 / levers.get(cyl.name, 0.3)
        else:
            f = 2000.0 * np.sin(q[:, 3] * 3.0)
        forces[cyl.name] = f
        util[cyl.name] = np.abs(f) / (supply * cyl.area_a_m2)
        pa = np.clip(np.maximum(f, 0) / cyl.area_a_m2 + 1e6, 0, 25e6)
        pb = np.clip(np.maximum(-f, 0) / cyl.area_b_m2 + 1e6, 0, 25e6)
        pressures[cyl.name] = (pa, pb)
    moments = {"theta0": 300.0 * np.cos(q[:, 0]), "theta1": moment1, "theta2": moment2}
    return {"forces": forces, "util": util, "pressures": pressures, "moments": moments}


def synthetic_twin(machine: Machine, t0: float, t1: float, rate_hz: float,
                   payload_kg: float = 400.0, phase: float = 0.0) -> dict[str, Any]:
    """A twin result (contract v1 shape) of the scripted cycle over [t0, t1] at ``rate_hz``."""
    n = max(int(np.floor((t1 - t0) * rate_hz + 1e-9)) + 1, 1)
    t = t0 + np.arange(n) / rate_hz
    q = scripted_q(t, phase)
    pay = scripted_payload(t, payload_kg, phase)
    loads = _loads(machine, q, pay)
    out: dict[str, Any] = {"t": t.tolist(), "q": q.tolist(), **frame_arrays(machine, q)}
    out["cylinder_forces"] = {k: v.tolist() for k, v in loads["forces"].items()}
    out["utilisation"] = {k: v.tolist() for k, v in loads["util"].items()}
    tau = np.stack([loads["moments"]["theta0"], loads["moments"]["theta1"],
                    -loads["moments"]["theta2"], loads["forces"][machine.cylinders[-1].name]], 1)
    out["joint_torques"] = tau.tolist()
    out["payload"] = {"t": t.tolist(), "kg": pay.tolist(), "std_kg": (0.02 * pay + 5).tolist()}
    return out


def synthetic_frame(machine: Machine, t: float, payload_kg: float = 400.0,
                    phase: float = 0.0) -> dict[str, Any]:
    """One live websocket frame (contract v1 shape) of the scripted cycle at time t [s]."""
    tw = synthetic_twin(machine, t, t, 1.0, payload_kg, phase)
    q = np.asarray(tw["q"])
    pay = scripted_payload(np.array([t]), payload_kg, phase)
    loads = _loads(machine, q, pay)
    pressures: dict[str, float] = {}
    for ch in machine.channels:
        if ch.quantity in ("pressure_a", "pressure_b"):
            pa, pb = loads["pressures"][ch.source]
            pressures[ch.name] = float((pa if ch.quantity == "pressure_a" else pb)[0])
    return {
        "t": t, "q": tw["q"][0],
        "poses": {k: v[0] for k, v in tw["poses"].items()},
        "cylinder_pins": {k: v[0] for k, v in tw["cylinder_pins"].items()},
        "cylinder_forces": {k: v[0] for k, v in tw["cylinder_forces"].items()},
        "utilisation": {k: v[0] for k, v in tw["utilisation"].items()},
        "payload_kg": float(pay[0]), "pressures": pressures,
    }


def synthetic_history(machine: Machine, t0: float, t1: float, channels: list[str],
                      max_points: int = 2000, payload_kg: float = 400.0,
                      phase: float = 0.0) -> dict[str, Any]:
    """Load history (contract v1 ``/history`` shape): min/max/mean per bucket of the scripted
    cycle sampled at 2 Hz (or finer for short ranges), at most ``max_points`` buckets."""
    rate = max(2.0, min(20.0, 4000.0 / max(t1 - t0, 1e-3)))
    n = max(int((t1 - t0) * rate) + 1, 2)
    t = np.linspace(t0, t1, n)
    q = scripted_q(t, phase)
    pay = scripted_payload(t, payload_kg, phase)
    loads = _loads(machine, q, pay)
    series: dict[str, F64] = {"payload": pay}
    for name, f in loads["forces"].items():
        series[f"force:{name}"] = f
    for name, m in loads["moments"].items():
        series[f"moment:{name}"] = m
    for ch in machine.channels:
        if ch.quantity in ("pressure_a", "pressure_b"):
            pa, pb = loads["pressures"][ch.source]
            series[ch.name] = pa if ch.quantity == "pressure_a" else pb
    buckets = max(1, min(max_points, n))
    edges = np.linspace(0, n, buckets + 1).astype(int)
    out: dict[str, Any] = {}
    for name in channels:
        if name not in series:
            continue
        v = series[name]
        bt, bmin, bmax, bmean = [], [], [], []
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            if b <= a:
                continue
            bt.append(float(t[a]))
            bmin.append(float(v[a:b].min()))
            bmax.append(float(v[a:b].max()))
            bmean.append(float(v[a:b].mean()))
        out[name] = {"t": bt, "min": bmin, "max": bmax, "mean": bmean}
    return {"channels": out}
