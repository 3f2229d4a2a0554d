"""Sample blocks for tests, demos and the API benchmark, tiled in time.

Two sources:

* :func:`kinematic_samples` — fast and exact: a periodic motion in rod space (periods 20–60 s,
  so 120 s tiles seamlessly), the joint motion from the inverse kinematics, the joint loads by
  inverse dynamics with a known payload schedule, and the pressures that produce them through
  Eq. 1–2 (friction included). A replay of these samples must give back the payload and forces.
* :func:`simulated_samples` — the machine-side simulator running a scenario that exists for the
  machine: the PATU 655's ``log-loading``, or the first scenario shipped with another machine
  (the Bobcat 435's ``dig-cycle``) (slow to compute; realistic noise and hydraulics).

:func:`tiled_blocks` repeats a recording back to back to cover any duration, cut into blocks
of ``block_s`` as the ingest daemon stores them.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import lru_cache

import numpy as np

from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays, SampleBlock

PAYLOAD_KG = 400.0
"""Payload held during the second half of every minute by :func:`kinematic_samples` [kg]."""


def payload_schedule(t_s: np.ndarray) -> np.ndarray:
    """Payload of :func:`kinematic_samples`: 0 in the first 30 s of each minute, then 400 kg."""
    return np.where(np.mod(t_s, 60.0) >= 30.0, PAYLOAD_KG, 0.0)


def kinematic_samples(machine: Machine, duration_s: float = 120.0, rate_hz: float = 100.0,
                      t0_s: float = 0.0) -> SampleArrays:
    """Exact sensor samples of a periodic motion with the payload of :func:`payload_schedule`.

    Rod positions s_k(t) = stroke·(0.5 + 0.3·sin(2π t / T_k + φ_k)) with T = 40, 30, 60 s;
    slew θ0(t) = 0.6·sin(2π t / 120 s). Pressures: pB = 2 MPa (raised when pA would fall below
    0.5 MPa), pA from Eq. 1 with the force that inverse dynamics needs at the joint
    (F = τ / (ds/dq), plus friction at the rod velocity). Values quantised at the channel
    resolutions.

    Returns:
        Samples with the machine's channels (all of them, including the optional slew angle).
    """
    from cranetwin.physics import (
        friction_force,
        inverse_dynamics,
        joints_from_cylinders,
        moment_arms,
    )

    n = int(round(duration_s * rate_hz))
    t = t0_s + np.arange(n) / rate_hz
    w = 2 * np.pi
    periods = [40.0, 30.0, 60.0, 20.0][: len(machine.cylinders)]
    phases = [0.0, 1.0, 2.0, 3.0]
    strokes = np.array([c.stroke_m for c in machine.cylinders])
    s = np.column_stack([0.5 + 0.3 * np.sin(w * t / p + ph) for p, ph in zip(periods, phases,
                                                                          strict=False)])
    sd = np.column_stack([0.3 * w / p * np.cos(w * t / p + ph) for p, ph in zip(periods, phases,
                                                                             strict=False)])
    s, sd = s * strokes, sd * strokes
    th = 0.6 * np.sin(w * t / 120.0)
    q = joints_from_cylinders(machine, s, th if len(machine.joints) > len(machine.cylinders)
                              else None)
    dt = 1.0 / rate_hz
    qd = np.gradient(q, dt, axis=0)
    qdd = np.gradient(qd, dt, axis=0)
    payload = payload_schedule(t)
    tau, _ = inverse_dynamics(machine, q, qd, qdd, payload)
    arms = moment_arms(machine, q)
    cols: dict[str, np.ndarray] = {}
    for k, c in enumerate(machine.cylinders):
        j = machine.joint_index(c.joint)
        f = tau[:, j] / arms[:, k] + friction_force(sd[:, k], c.friction)
        pb = np.full(n, 2.0e6)
        pa = (f + pb * c.area_b_m2) / c.area_a_m2
        low = pa < 0.5e6
        pa[low] = 0.5e6
        pb[low] = (pa[low] * c.area_a_m2 - f[low]) / c.area_b_m2
        cols[("pressure_a", c.name)] = pa  # type: ignore[index]
        cols[("pressure_b", c.name)] = pb  # type: ignore[index]
        cols[("position", c.name)] = s[:, k]  # type: ignore[index]
    for d in machine.torque_drives:
        j = machine.joint_index(d.joint)
        thd = qd[:, j]
        cols[("torque", d.name)] = tau[:, j] + friction_force(thd, d.friction)  # type: ignore
    for jn in machine.joints:
        cols[("angle", jn.name)] = q[:, machine.joint_index(jn.name)]  # type: ignore[index]
    names, values = [], []
    for ch in machine.channels:
        v = cols.get((ch.quantity, ch.source))  # type: ignore[call-overload]
        if v is None:
            continue
        names.append(ch.name)
        values.append(np.round(v / ch.resolution) * ch.resolution)
    return SampleArrays(machine.name, t, tuple(names), np.column_stack(values),
                        period_ns=int(round(1e9 / rate_hz)))


def default_scenario(model: str) -> str:
    """The scenario :func:`simulated_samples` runs for built-in machine ``model``: the first one
    shipped with the machine (``machines/scenarios/<model>/``), else the built-in
    ``log-loading`` (the PATU 655's)."""
    from cranetwin.sim.scenario import machine_scenarios

    own = machine_scenarios(model)
    return own[0] if own else "log-loading"


@lru_cache(maxsize=4)
def simulated_samples(model: str = "patu655", base_s: float = 120.0, seed: int = 0,
                      scenario: str | None = None) -> SampleArrays:
    """Sensor samples of ``base_s`` seconds of a scenario of ``model``, t from 0 [s].

    Args:
        model: Built-in machine name.
        base_s: Seconds to simulate; a scenario file of the machine (a single work cycle) is
            simulated for at most its own duration (:func:`tiled_blocks` repeats it).
        seed: Seed of the sensors (built-in scenarios run with their default seed, as before).
        scenario: Scenario name (default :func:`default_scenario`).
    """
    from cranetwin.sim import load_scenario, simulate
    from cranetwin.sim.scenario import BUILTIN

    name = scenario if scenario is not None else default_scenario(model)
    if name in BUILTIN:
        sc = load_scenario(name)
        duration = base_s
    else:
        sc = load_scenario(name, machine=model)
        duration = min(base_s, sc.duration_s)
    rec = simulate(load_machine(model), sc, duration_s=duration, seed=seed)
    return rec.samples


def tiled_blocks(machine_id: str, machine: Machine, start_s: float, duration_s: float,
                 block_s: float = 1.0, base: SampleArrays | None = None,
                 seq0: int = 0, origin_s: float | None = None) -> Iterator[SampleBlock]:
    """Blocks of ``duration_s`` seconds starting at ``start_s`` (epoch seconds, a whole number of
    sample periods), the base recording repeated.

    Args:
        machine_id: Machine the blocks belong to.
        machine: Its description (channel resolutions).
        start_s: Time of the first sample [s].
        duration_s: Span to cover [s].
        block_s: Samples per block / sample rate [s].
        base: Recording to tile (default :func:`simulated_samples`).
        seq0: Sequence number of the first block.
        origin_s: Time at which the base recording starts a repetition (default ``start_s``);
            give the same origin to consecutive calls to continue the motion seamlessly.
    """
    src = base if base is not None else simulated_samples(machine.name)
    if src.period_ns is not None:
        period_ns = src.period_ns
    else:
        from cranetwin.signal import nominal_period

        period_ns = int(round(nominal_period(src.t_s) * 1e9))
    n_base = src.t_s.shape[0]
    per_block = max(1, int(round(block_s * 1e9 / period_ns)))
    n_total = int(round(duration_s * 1e9 / period_ns))
    res = tuple(machine.channel(c).resolution if c in {ch.name for ch in machine.channels}
                else 0.0 for c in src.channels)
    vals = src.values
    start_ns = int(round(start_s * 1e9))
    shift = int(round(((start_s - origin_s) if origin_s is not None else 0.0) * 1e9 / period_ns))
    seq = seq0
    for k0 in range(0, n_total, per_block):
        k1 = min(n_total, k0 + per_block)
        idx = (np.arange(k0, k1) + shift) % n_base
        block_vals = vals[idx]
        if np.isnan(block_vals).all():
            continue
        yield SampleBlock(machine_id=machine_id, seq=seq, t0_ns=start_ns + k0 * period_ns,
                          period_ns=period_ns, channels=src.channels, resolution=res,
                          values=np.ascontiguousarray(block_vals))
        seq += 1
