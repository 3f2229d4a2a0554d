"""Hydraulics and integration of the independent crane model (:mod:`cranetwin.testing.indep_crane`).

* **Hydraulics** per cylinder: a 4/3 critically lapped valve, Q = K·U·sign(Δp)·sqrt(|Δp|)
  (regularised below ``dp_laminar_pa``), spool U with a first-order lag, chamber pressures
  ṗ = β/V·(Q ∓ A·v) with V = V_dead + A·(travel), β the oil and hose in series, a relief and an
  anti-cavitation valve on each chamber. Friction Fc·tanh(v/vc) + b·v. End stops as stiff
  spring-dampers (scenarios stay off them). The slewing drive is a torque with a first-order
  lag, its own Coulomb + viscous friction.
* **Cylinder force**, the truth the twin is compared with: F = pA·A1 − pB·A2 − F_fr(v) [N], the
  net rod force on the structure (docs/PHYSICS.md), > 0 pushing. The slew torque channel is the
  drive's torque before its friction (the twin subtracts the drive friction itself).
* Integrated with ``scipy.integrate.solve_ivp`` (LSODA, ``max_step``) in segments between
  payload steps (the mass jumps at the tip), sampled at 100 Hz (:func:`simulate`).

numpy + scipy only, like the model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_ivp

from cranetwin.testing.indep_crane import (
    NC,
    NQ,
    CraneParams,
    Cyl,
    Dynamics,
    dynamics,
    potential_energy,
)

F64 = npt.NDArray[np.float64]


# --- hydraulics ------------------------------------------------------------------------------

def _orifice(p: CraneParams, dp: F64 | float) -> F64:
    """sign(Δp)·sqrt(|Δp|), linear below ``dp_laminar_pa`` (smooth) [√Pa]."""
    d = np.asarray(dp, dtype=np.float64)
    return np.asarray(d / np.sqrt(np.sqrt(d * d + p.dp_laminar_pa ** 2)), dtype=np.float64)


def valve_flows(p: CraneParams, u: F64, pa: F64, pb: F64, cyl: tuple[Cyl, ...]) -> tuple[F64, F64]:
    """Flows into chamber A and B [m³/s], spool voltages u (3,) [V]: a critically lapped 4/3
    valve, P→A and B→T for u > 0, P→B and A→T for u < 0, plus relief and anti-cavitation."""
    k = np.array([c.flow_gain for c in cyl])
    up, un = np.maximum(u, 0.0), np.minimum(u, 0.0)
    qa = k * (up * _orifice(p, p.supply_pa - pa) + un * _orifice(p, pa - p.tank_pa))
    qb = k * (-up * _orifice(p, pb - p.tank_pa) - un * _orifice(p, p.supply_pa - pb))
    for pc, qc in ((pa, qa), (pb, qb)):
        qc -= p.relief_gain * np.maximum(pc - p.relief_pa, 0.0)
        qc += p.anticav_gain * np.maximum(p.tank_pa - pc, 0.0)
    return qa, qb


def friction(v: F64 | float, fc: F64 | float, vc: F64 | float, b: F64 | float) -> F64:
    """Coulomb (smooth) + viscous friction opposing v [N or N·m]."""
    return np.asarray(fc * np.tanh(np.asarray(v) / vc) + b * np.asarray(v), dtype=np.float64)


# --- state and right-hand side ---------------------------------------------------------------

# state x: q (4), qd (4), pA (3), pB (3), spool u (3) [V], slew torque T [N·m]
SQ, SQD, SPA, SPB, SU, ST = slice(0, 4), slice(4, 8), slice(8, 11), slice(11, 14), slice(14, 17), 17
NX = 18

Commands = Callable[[float, F64], tuple[F64, float]]
"""(t, x) → (valve voltages (3,) [V], slew torque command [N·m])."""


@dataclass(frozen=True)
class Forces:
    """Forces at one state: cylinder force F = pA·A1 − pB·A2 − F_fr (3,) [N], end-stop force
    (3,) [N], rod positions s (3,) [m] and velocities v (3,) [m/s]."""

    cylinder: F64
    stop: F64
    s: F64
    v: F64


def cylinder_forces(p: CraneParams, x: F64, dyn: Dynamics) -> Forces:
    """Eq.-1-like cylinder forces and end stops from state x and the geometry in ``dyn``."""
    a1 = np.array([c.a1 for c in p.cyl])
    a2 = np.array([c.a2 for c in p.cyl])
    closed = np.array([c.closed_m for c in p.cyl])
    stroke = np.array([c.stroke_m for c in p.cyl])
    s = dyn.length - closed
    v = dyn.dldq @ x[SQD]
    fr = friction(v, np.array([c.fc_n for c in p.cyl]), np.array([c.vc_mps for c in p.cyl]),
                  np.array([c.b_nspm for c in p.cyl]))
    f = x[SPA] * a1 - x[SPB] * a2 - fr
    pen_lo, pen_hi = np.minimum(s, 0.0), np.maximum(s - stroke, 0.0)
    stop = -p.stop_k_npm * (pen_lo + pen_hi) - p.stop_c_nspm * v * ((pen_lo < 0) | (pen_hi > 0))
    return Forces(f, stop, s, v)


def rhs(p: CraneParams, t: float, x: F64, payload_kg: float, commands: Commands) -> F64:
    """dx/dt of the state x (18,)."""
    q, qd = x[SQ], x[SQD]
    dyn = dynamics(p, q, qd, payload_kg)
    fo = cylinder_forces(p, x, dyn)
    tau = dyn.qg + dyn.dldq.T @ (fo.cylinder + fo.stop)
    tau[0] += x[ST] - float(friction(qd[0], p.slew_fc_nm, p.slew_vc_rps, p.slew_b_nmsprad))
    qdd = np.linalg.solve(dyn.m, tau - dyn.c)
    u_cmd, t_cmd = commands(t, x)
    qa, qb = valve_flows(p, x[SU], x[SPA], x[SPB], p.cyl)
    a1 = np.array([c.a1 for c in p.cyl])
    a2 = np.array([c.a2 for c in p.cyl])
    stroke = np.array([c.stroke_m for c in p.cyl])
    s = np.clip(fo.s, 0.0, stroke)
    va = p.dead_volume_m3 + a1 * s
    vb = p.dead_volume_m3 + a2 * (stroke - s)
    dx = np.empty(NX)
    dx[SQ] = qd
    dx[SQD] = qdd
    dx[SPA] = p.beta_pa / va * (qa - a1 * fo.v)
    dx[SPB] = p.beta_pa / vb * (qb + a2 * fo.v)
    dx[SU] = (np.clip(u_cmd, -10.0, 10.0) - x[SU]) / p.spool_tau_s
    dx[ST] = (float(np.clip(t_cmd, -p.slew_max_nm, p.slew_max_nm)) - x[ST]) / p.slew_tau_s
    return dx


def holding_state(p: CraneParams, q: F64, payload_kg: float, p_low_pa: float = 2.0e6) -> F64:
    """A state at rest at q: chamber pressures that hold the boom against gravity (the lower
    chamber at ``p_low_pa``), spools closed, no slew torque. Shape (18,)."""
    dyn = dynamics(p, q, np.zeros(NQ), payload_kg)
    # each cylinder drives one joint: F_k·∂ℓ_k/∂q_j(k) = −Q_g,j(k)
    need = np.array([-dyn.qg[1] / dyn.dldq[0, 1], -dyn.qg[2] / dyn.dldq[1, 2],
                     -dyn.qg[3] / dyn.dldq[2, 3]])
    x = np.zeros(NX)
    x[SQ] = q
    for k, c in enumerate(p.cyl):
        if need[k] >= 0:
            x[SPB.start + k] = p_low_pa
            x[SPA.start + k] = (need[k] + p_low_pa * c.a2) / c.a1
        else:
            x[SPA.start + k] = p_low_pa
            x[SPB.start + k] = (p_low_pa * c.a1 - need[k]) / c.a2
    return x


# --- simulation ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Scenario:
    """A run: duration [s], initial state (18,), commands, payload steps [(t_s, kg), …] (the
    payload before the first step is ``payload0_kg``)."""

    name: str
    duration_s: float
    x0: F64
    commands: Commands
    payload0_kg: float = 0.0
    payload_steps: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class Run:
    """Sampled output of :func:`simulate` (n samples at ``rate_hz``).

    Attributes:
        t_s: (n,) [s from start]. q, qd: (n, 4). qdd: (n, 4) (from the equations of motion).
        pa_pa, pb_pa: chamber pressures (n, 3) [Pa]. length_m: pin-to-pin lengths (n, 3) [m].
        s_m, v_mps: rod position (stroke) and velocity (n, 3). force_n: cylinder force
        pA·A1 − pB·A2 − F_fr (n, 3) [N]. stop_n: end-stop force (n, 3) [N] (0 off the stops).
        slew_torque_nm: drive torque (n,). payload_kg: (n,). energy_j: kinetic + gravity (n,).
        nfev: right-hand-side evaluations.
    """

    name: str
    t_s: F64
    q: F64
    qd: F64
    qdd: F64
    pa_pa: F64
    pb_pa: F64
    length_m: F64
    s_m: F64
    v_mps: F64
    force_n: F64
    stop_n: F64
    slew_torque_nm: F64
    payload_kg: F64
    energy_j: F64
    nfev: int = 0

    def save(self, path: str) -> None:
        """Write to an ``.npz`` file."""
        arrays = {k: getattr(self, k) for k in self.__dataclass_fields__
                  if k not in ("name", "nfev")}
        np.savez(path, name=np.array(self.name), nfev=np.array(self.nfev), **arrays)

    @staticmethod
    def load(path: str) -> Run:
        """Read a file of :meth:`save`."""
        with np.load(path) as z:
            kw = {k: z[k] for k in z.files if k not in ("name", "nfev")}
            return Run(name=str(z["name"]), nfev=int(z["nfev"]), **kw)


def simulate(p: CraneParams, sc: Scenario, rate_hz: float = 100.0, max_step_s: float = 2e-3,
             method: str = "LSODA", rtol: float = 1e-7, atol: F64 | None = None) -> Run:
    """Integrate the scenario and sample it at ``rate_hz``.

    Args:
        p: Crane parameters.
        sc: Scenario.
        rate_hz: Output rate [Hz].
        max_step_s: Largest integrator step [s].
        method: ``solve_ivp`` method (stiff-aware: LSODA, Radau, BDF).
        rtol, atol: Tolerances (atol default: 1e-8 m or rad, 1e-7 per s, 1 Pa, 1e-6 V, 1e-3 N·m).
    """
    if atol is None:
        atol = np.concatenate([np.full(4, 1e-8), np.full(4, 1e-7), np.full(6, 1.0),
                               np.full(3, 1e-6), [1e-3]])
    n = int(round(sc.duration_s * rate_hz)) + 1
    t_out = np.arange(n) / rate_hz
    edges = [0.0] + [t for t, _ in sc.payload_steps if 0 < t < sc.duration_s] + [sc.duration_s]
    masses_kg = [sc.payload0_kg] + [m for t, m in sc.payload_steps if 0 < t < sc.duration_s]
    xs = np.empty((n, NX))
    pay = np.empty(n)
    x = sc.x0.astype(np.float64).copy()
    nfev = 0
    for seg, (t0, t1) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        m = masses_kg[seg]
        last = seg == len(edges) - 2
        sel = (t_out >= t0) & ((t_out < t1) | (last & (t_out <= t1)))
        sol = solve_ivp(lambda t, y, m=m: rhs(p, t, y, m, sc.commands), (t0, t1), x,
                        method=method, max_step=max_step_s, rtol=rtol, atol=atol,
                        dense_output=True)
        if not sol.success:
            raise RuntimeError(f"{sc.name}: integration failed at t={sol.t[-1]:.3f} s: "
                               f"{sol.message}")
        nfev += int(sol.nfev)
        if sel.any():
            xs[sel] = sol.sol(t_out[sel]).T
        pay[sel] = m
        x = np.asarray(sol.y[:, -1], dtype=np.float64)
    return _sampled(p, sc.name, t_out, xs, pay, nfev)


def _sampled(p: CraneParams, name: str, t: F64, xs: F64, pay: F64, nfev: int) -> Run:
    n = t.shape[0]
    qdd = np.empty((n, NQ))
    length = np.empty((n, NC))
    s = np.empty((n, NC))
    v = np.empty((n, NC))
    force = np.empty((n, NC))
    stop = np.empty((n, NC))
    kin = np.empty(n)
    zero = lambda t, x: (np.zeros(NC), 0.0)  # noqa: E731 — commands do not enter qdd
    for i in range(n):
        x = xs[i]
        dyn = dynamics(p, x[SQ], x[SQD], float(pay[i]))
        fo = cylinder_forces(p, x, dyn)
        qdd[i] = rhs(p, float(t[i]), x, float(pay[i]), zero)[SQD]
        length[i], s[i], v[i], force[i], stop[i] = dyn.length, fo.s, fo.v, fo.cylinder, fo.stop
        kin[i] = 0.5 * x[SQD] @ dyn.m @ x[SQD]
    energy = kin + np.array([potential_energy(p, xs[i, SQ], float(pay[i])) for i in range(n)])
    return Run(name, t, xs[:, SQ].copy(), xs[:, SQD].copy(), qdd, xs[:, SPA].copy(),
               xs[:, SPB].copy(), length, s, v, force, stop, xs[:, ST].copy(), pay, energy, nfev)
